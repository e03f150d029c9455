"""Running a trained encoder outside training: ONNX Runtime (default) or PyTorch.

:func:`load_encoder` returns a :class:`LoadedEncoder` whose ``package`` says what the encoder expects
(``image_size``) and what goes into its triplanes (decoder, scene bounds) and whose ``run`` maps
images (B, 3, S, S) float32 in [-1, 1] to planes (B, 3, 32, T, T) float32.

* ``onnx``: an ``.onnx`` file plus its ``MODEL.json`` sidecar (:mod:`lp3d.model_package`).
* ``torch``: a plain state-dict checkpoint (``torch.load(weights_only=True)``, never unpickling
  code). Two layouts are understood: ``{"config": EncoderConfig dict, "encoder": state dict,
  "decoder": {w0, b0, w1, b1}, "bounds": {box_warp, ray_start, ray_end}}`` and the training
  checkpoint of ``python -m lp3d.train`` (``format`` "lp3d-train-checkpoint-v1", its ``student`` state
  dict and ``scene``). Missing decoder/bounds may come from a ``.json`` sidecar beside the checkpoint.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from lp3d.model_package import ModelPackage, ModelPackageError, load_model_package, sidecar_path
from lp3d.settings import N_CHANNELS

__all__ = ["DEFAULT_MODEL", "Backend", "LoadedEncoder", "load_encoder"]

Backend = Literal["onnx", "torch"]

#: The shipped model (may not exist until one is trained and exported).
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "small.onnx"


@dataclass
class LoadedEncoder:
    """An encoder ready to run: ``run(images (B, 3, S, S) float32) -> planes (B, 3, 32, T, T) float32``."""

    package: ModelPackage
    backend: Backend
    run: Callable[[np.ndarray], np.ndarray]
    description: str


def _reshape_planes(out: np.ndarray, batch: int, where: str) -> np.ndarray:
    """Encoder output (B, 3, 32, T, T) or (B, 96, T, T) -> (B, 3, 32, T, T) float32, checked."""
    out = np.asarray(out, dtype=np.float32)
    if out.ndim == 4 and out.shape[1] == 3 * N_CHANNELS:
        out = out.reshape(out.shape[0], 3, N_CHANNELS, *out.shape[2:])
    if out.ndim != 5 or out.shape[:3] != (batch, 3, N_CHANNELS) or out.shape[3] != out.shape[4]:
        raise ModelPackageError(f"{where}: output has shape {out.shape}, expected ({batch}, 3, 32, T, T)")
    if not np.all(np.isfinite(out)):
        raise ModelPackageError(f"{where}: encoder produced NaN/Inf")
    return out


# ---------------------------------------------------------------------------------------------- onnx


def _load_onnx(path: Path) -> LoadedEncoder:
    package = load_model_package(path)
    if not path.is_file():
        raise ModelPackageError(f"{path}: no such model file")
    try:
        import onnxruntime as ort
    except ImportError as e:
        raise ModelPackageError(
            f"the onnx backend needs onnxruntime (pip install onnxruntime): {e}"
        ) from None
    options = ort.SessionOptions()
    options.log_severity_level = 3  # errors only: warnings about unused initialisers are noise here
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types (InvalidProtobuf, Fail, ...)
        raise ModelPackageError(f"{path}: cannot load the ONNX model ({type(e).__name__}: {e})") from None
    inputs = session.get_inputs()
    if len(inputs) != 1:
        raise ModelPackageError(f"{path}: expected one input (the image), found {len(inputs)}")
    inp = inputs[0]
    shape = list(inp.shape)
    s = package.image_size
    if len(shape) != 4 or shape[1] not in (3, "3") or any(isinstance(d, int) and d != s for d in shape[2:]):
        raise ModelPackageError(
            f"{path}: input {inp.name!r} has shape {shape}, but the package says (B, 3, {s}, {s})"
        )
    fixed_batch = shape[0] if isinstance(shape[0], int) else None

    def run(images: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(images, dtype=np.float32)
        if fixed_batch is not None and x.shape[0] != fixed_batch:
            # Exported with a static batch: run that many at a time.
            if fixed_batch != 1:
                raise ModelPackageError(f"{path}: the model only accepts batches of exactly {fixed_batch}")
            return np.concatenate([run(x[i : i + 1]) for i in range(x.shape[0])])
        out = session.run(None, {inp.name: x})[0]
        return _reshape_planes(out, x.shape[0], str(path))

    return LoadedEncoder(package, "onnx", run, f"{path.name} (onnxruntime {ort.__version__}, CPU)")


# --------------------------------------------------------------------------------------------- torch


def _as_mapping(value: Any, what: str, where: Path) -> dict[str, Any]:
    """A dict from a dict or a JSON string (checkpoints store configs either way)."""
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except json.JSONDecodeError as e:
            raise ModelPackageError(f"{where}: {what} is not valid JSON ({e})") from None
    if not isinstance(value, Mapping):
        raise ModelPackageError(f"{where}: {what} must be a dict, got {type(value).__name__}")
    return dict(value)


def _strip(state: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    return {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}


def _checkpoint_file(p: Path) -> Path:
    """A checkpoint file; a training run folder means its latest ``checkpoints/step-*.pt``."""
    if p.is_dir():
        found = sorted((p / "checkpoints").glob("step-*.pt")) or sorted(p.glob("*.pt"))
        if not found:
            raise ModelPackageError(f"{p}: folder holds no checkpoints (expected checkpoints/step-*.pt)")
        return found[-1]
    if not p.is_file():
        raise ModelPackageError(f"{p}: no such checkpoint file")
    return p


def _load_torch(path: Path) -> LoadedEncoder:
    try:
        import torch
    except ImportError as e:
        raise ModelPackageError(f"the torch backend needs PyTorch: {e}") from None
    from lp3d.encoder import EncoderConfig, build_encoder

    p = _checkpoint_file(path)
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for non-checkpoints (UnpicklingError, RuntimeError, ...)
        raise ModelPackageError(f"{p}: cannot be read as a plain state-dict checkpoint ({e})") from None
    if not isinstance(ckpt, Mapping):
        raise ModelPackageError(f"{p}: a checkpoint must hold a dict, got {type(ckpt).__name__}")
    layout_hint = (
        f"{p}: checkpoint layout not understood (keys {sorted(map(str, ckpt))[:12]}); expected "
        "{'config': EncoderConfig dict, 'encoder': state dict, 'decoder': {w0, b0, w1, b1}, "
        "'bounds': {box_warp, ray_start, ray_end}} or a python -m lp3d.train checkpoint"
    )
    # The encoder's configuration: an EncoderConfig dict, or a training config holding one.
    raw_cfg = ckpt.get("encoder_config", ckpt.get("config"))
    if raw_cfg is None:
        raise ModelPackageError(layout_hint)
    cfg_dict = _as_mapping(raw_cfg, "config", p)
    if isinstance(cfg_dict.get("encoder"), Mapping):
        cfg_dict = dict(cfg_dict["encoder"])
    try:
        config = EncoderConfig.from_dict(cfg_dict)
    except (TypeError, ValueError) as e:
        raise ModelPackageError(
            f"{p}: the encoder configuration cannot be read by this version ({e})"
        ) from None
    # The encoder's weights, and the decoder's where the checkpoint has them.
    student = ckpt.get("student") if isinstance(ckpt.get("student"), Mapping) else None
    if isinstance(ckpt.get("encoder"), Mapping):
        state = dict(ckpt["encoder"])
    elif student is not None:
        state = _strip(student, "encoder.")
    else:
        raise ModelPackageError(layout_hint)
    # A training checkpoint's student may add a learned mean triplane to the encoder's output.
    offset = student.get("plane_offset") if student is not None else ckpt.get("plane_offset")
    if offset is not None:
        offset = torch.as_tensor(offset).float()
    decoder: dict[str, Any] | None = None
    if isinstance(ckpt.get("decoder"), Mapping):
        decoder = dict(ckpt["decoder"])
    elif student is not None and "decoder.w0" in student:
        decoder = _strip(student, "decoder.")
    bounds_raw = ckpt.get("bounds", ckpt.get("scene"))
    bounds = _as_mapping(bounds_raw, "bounds", p) if bounds_raw is not None else None
    side = sidecar_path(p)
    sidecar = load_model_package(side) if (decoder is None or bounds is None) and side.is_file() else None
    if decoder is None and sidecar is None:
        raise ModelPackageError(
            f"{p}: the checkpoint carries no decoder weights ('decoder') and no {side.name}"
        )
    if bounds is None and sidecar is None:
        raise ModelPackageError(f"{p}: the checkpoint carries no scene bounds ('bounds') and no {side.name}")

    encoder = build_encoder(config)
    try:
        encoder.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).splitlines()[0]
        raise ModelPackageError(
            f"{p}: encoder weights do not fit configuration {config.name!r}: {first}"
        ) from None
    encoder.eval()

    def array(v: Any) -> np.ndarray:
        return v.detach().cpu().numpy() if hasattr(v, "detach") else np.asarray(v)

    try:
        if decoder is not None:
            w0, b0, w1, b1 = (np.asarray(array(decoder[k]), np.float32) for k in ("w0", "b0", "w1", "b1"))
        else:
            assert sidecar is not None
            w0, b0, w1, b1 = sidecar.decoder
        if bounds is not None:
            box_warp, ray_start, ray_end = (float(bounds[k]) for k in ("box_warp", "ray_start", "ray_end"))
        else:
            assert sidecar is not None
            box_warp, ray_start, ray_end = sidecar.box_warp, sidecar.ray_start, sidecar.ray_end
    except (KeyError, TypeError, ValueError) as e:
        raise ModelPackageError(f"{p}: malformed decoder or bounds ({type(e).__name__}: {e})") from None
    package = ModelPackage(
        sidecar=side,
        model_path=p,
        config_name=config.name,
        image_size=config.image_size,
        triplane_resolution=config.triplane_resolution,
        box_warp=box_warp,
        ray_start=ray_start,
        ray_end=ray_end,
        w0=w0,
        b0=b0,
        w1=w1,
        b1=b1,
        encoder_config=config.to_dict(),
    )
    try:
        package.triplane(np.zeros((3, N_CHANNELS, 2, 2), np.float32))  # validates decoder and bounds
    except ValueError as e:
        raise ModelPackageError(f"{p}: bad decoder or bounds ({e})") from None

    def run(images: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            out = encoder(torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)))
            if offset is not None:
                out = out + offset
        return _reshape_planes(out.float().numpy(), images.shape[0], str(p))

    return LoadedEncoder(package, "torch", run, f"{p.name} (torch {torch.__version__}, CPU)")


def load_encoder(path: str | os.PathLike[str], backend: Backend | None = None) -> LoadedEncoder:
    """Load an encoder; ``backend`` None picks ``torch`` for ``.pt``/``.pth``/folders, else ``onnx``.

    Raises :class:`~lp3d.model_package.ModelPackageError` (a ValueError) with a clear message for a
    missing file or sidecar, an unreadable model, or a layout that does not fit.
    """
    p = Path(path)
    if backend is None:
        backend = "torch" if p.suffix.lower() in (".pt", ".pth") or p.is_dir() else "onnx"
    if backend == "onnx":
        if p.suffix.lower() in (".pt", ".pth"):
            raise ModelPackageError(f"{p}: a torch checkpoint; use --backend torch (or export it to ONNX)")
        return _load_onnx(p)
    if backend == "torch":
        if p.suffix.lower() == ".onnx":
            raise ModelPackageError(f"{p}: an ONNX model; use --backend onnx")
        return _load_torch(p)
    raise ModelPackageError(f"unknown backend {backend!r} (use onnx or torch)")
