"""Running a trained encoder outside training: ONNX Runtime (default) or PyTorch.

:func:`load_encoder` returns a :class:`LoadedEncoder` whose ``package`` says what the encoder expects
(``image_size``) and what goes into its triplanes (decoder, scene bounds) and whose ``run`` maps
images (B, 3, S, S) float32 in [-1, 1] to planes (B, 3, 32, T, T) float32.

* ``onnx``: an ``.onnx`` file plus its ``MODEL.json`` sidecar (:mod:`lp3d.lift.model_package`).
* ``torch``: a plain state-dict checkpoint (``torch.load(weights_only=True)``, never unpickling
  code). Two layouts are understood: ``{"config": EncoderConfig dict, "encoder": state dict,
  "decoder": {w0, b0, w1, b1}, "bounds": {box_warp, ray_start, ray_end}}`` and the training
  checkpoint of ``python -m lp3d.train`` (``format`` "lp3d-train-checkpoint-v1", its ``student`` state
  dict and ``scene``). Missing decoder/bounds may come from a ``.json`` sidecar beside the checkpoint.

**Super-resolution.** A package may carry a super-resolution network (SR) beside the encoder, which
turns the renderer's raw *feature* image into the final image, as EG3D's does (paper Eq. 2, with the
constant w of the paper's supplement, so it needs nothing but the features). :func:`load_superres`
returns it as a :class:`LoadedSuperres` (or None when the package has none); the Python API in one
call::

    import lp3d_render
    from lp3d.lift.inference import load_superres

    sr = load_superres()                        # the shipped model's, or load_superres("MODEL.onnx")
    out = lp3d_render.render(tri, camera, resolution=sr.input_resolution, outputs=["features"])
    image = sr(out["features"])                 # (3, R_out, R_out) float32 in about [-1, 1]

``onnx``: the sidecar's ``superres`` entry (``MODEL.superres.onnx``, its SHA-256 checked on load).
``torch``: the checkpoint's ``superres`` (``{"config": SuperresConfig dict, "state": state dict}``,
written by ``lp3d export --weights``) or, for a training checkpoint of the paper recipe, its
student's trained SR. The CPU recipe trains none; ``python -m lp3d.training.superres_fit`` fits one for
such a model.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from lp3d.lift.model_package import (
    ModelPackage,
    ModelPackageError,
    SuperresEntry,
    load_model_package,
    sidecar_path,
    verify_superres_file,
)
from lp3d.render.settings import N_CHANNELS

__all__ = [
    "DEFAULT_MODEL",
    "Backend",
    "LoadedEncoder",
    "LoadedSuperres",
    "load_encoder",
    "load_superres",
    "superresolve",
]

Backend = Literal["onnx", "torch"]

#: The shipped model (may not exist until one is trained and exported).
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "small.onnx"


@dataclass
class LoadedSuperres:
    """A super-resolution network ready to run: ``sr(features) -> image``.

    ``features`` is the renderer's raw feature image, (B, 32, R, R) or (32, R, R) float32 with
    ``R = input_resolution``; the image is (B, 3, R_out, R_out) (or (3, R_out, R_out)) float32 in about
    [-1, 1] (``lp3d.images.rgb_to_uint8`` clips), ``R_out = output_resolution``. ``package`` is the
    model package it belongs to: its decoder is the one whose features the network was made for.
    """

    package: ModelPackage
    backend: Backend
    input_resolution: int
    output_resolution: int
    in_channels: int
    description: str
    _run: Callable[[np.ndarray], np.ndarray]

    def __call__(self, features: np.ndarray) -> np.ndarray:
        x = np.asarray(features)
        single = x.ndim == 3
        if single:
            x = x[None]
        c, r = self.in_channels, self.input_resolution
        if x.ndim != 4 or x.shape[1:] != (c, r, r):
            raise ValueError(
                f"super-resolution input must be features ({c}, {r}, {r}) or (B, {c}, {r}, {r}) (a raw "
                f"render at resolution={r} with outputs=['features']), got shape {tuple(np.shape(features))}"
            )
        if x.shape[0] == 0:
            raise ValueError("super-resolution input has an empty batch")
        x = np.ascontiguousarray(x, dtype=np.float32)
        if not np.all(np.isfinite(x)):
            raise ValueError("super-resolution input contains NaN/Inf")
        out = np.asarray(self._run(x), dtype=np.float32)
        want = (x.shape[0], 3, self.output_resolution, self.output_resolution)
        if out.shape != want:
            raise ModelPackageError(f"{self.description}: output has shape {out.shape}, expected {want}")
        if not np.all(np.isfinite(out)):
            raise ModelPackageError(f"{self.description}: produced NaN/Inf")
        return out[0] if single else out

    run = __call__

    def accepts(self, triplane: Any) -> bool:
        """Whether ``triplane`` (a TriplaneData) has this package's decoder and scene bounds, i.e.
        renders the feature space the network was made for."""
        pkg = self.package
        same = all(
            np.array_equal(np.asarray(getattr(triplane, k), np.float32), a)
            for k, a in zip(("w0", "b0", "w1", "b1"), pkg.decoder, strict=True)
        )
        bounds = (float(triplane.box_warp), float(triplane.ray_start), float(triplane.ray_end))
        return same and bounds == (pkg.box_warp, pkg.ray_start, pkg.ray_end)


@dataclass
class LoadedEncoder:
    """An encoder ready to run: ``run(images (B, 3, S, S) float32) -> planes (B, 3, 32, T, T) float32``.

    ``superres`` is the package's super-resolution network when ``load_encoder(..., superres=True)``
    was asked for it and the package has one, else None."""

    package: ModelPackage
    backend: Backend
    run: Callable[[np.ndarray], np.ndarray]
    description: str
    superres: LoadedSuperres | None = None


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


def _ort_session(path: Path) -> Any:
    """An onnxruntime CPU session of ``path``; clear errors for a missing onnxruntime or a bad file."""
    try:
        import onnxruntime as ort
    except ImportError as e:
        raise ModelPackageError(
            f"the onnx backend needs onnxruntime (pip install onnxruntime): {e}"
        ) from None
    options = ort.SessionOptions()
    options.log_severity_level = 3  # errors only: warnings about unused initialisers are noise here
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types (InvalidProtobuf, Fail, ...)
        raise ModelPackageError(f"{path}: cannot load the ONNX model ({type(e).__name__}: {e})") from None


def _load_onnx_superres(package: ModelPackage, entry: SuperresEntry) -> LoadedSuperres:
    """The package's SR network from its ONNX file, checked against the sidecar's entry."""
    verify_superres_file(entry)
    session = _ort_session(entry.path)
    import onnxruntime as ort  # present: the session was made

    where = f"{entry.path} (the package's 'superres')"
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1 or len(outputs) != 1:
        raise ModelPackageError(
            f"{where}: expected one input (features) and one output (image), found {len(inputs)} and "
            f"{len(outputs)}"
        )
    c, r, ro = entry.in_channels, entry.input_resolution, entry.output_resolution
    for what, shape, want in (
        ("input", inputs[0].shape, (c, r, r)),
        ("output", outputs[0].shape, (3, ro, ro)),
    ):
        dims = ", ".join(map(str, want))
        if len(shape) != 4 or any(
            isinstance(d, int) and d != w for d, w in zip(shape[1:], want, strict=True)
        ):
            raise ModelPackageError(
                f"{where}: {what} has shape {list(shape)}, but the sidecar says (B, {dims})"
            )
    name = inputs[0].name
    fixed_batch = inputs[0].shape[0] if isinstance(inputs[0].shape[0], int) else None

    def run(features: np.ndarray) -> np.ndarray:
        if fixed_batch is not None and features.shape[0] != fixed_batch:
            if fixed_batch != 1:
                raise ModelPackageError(f"{where}: the model only accepts batches of exactly {fixed_batch}")
            return np.concatenate([run(features[i : i + 1]) for i in range(features.shape[0])])
        return session.run(None, {name: features})[0]

    return LoadedSuperres(
        package,
        "onnx",
        r,
        ro,
        c,
        f"{entry.path.name} (onnxruntime {ort.__version__}, CPU)",
        run,
    )


def _load_onnx(path: Path, *, superres: bool = False) -> LoadedEncoder:
    package = load_model_package(path)
    if not path.is_file():
        raise ModelPackageError(f"{path}: no such model file")
    session = _ort_session(path)
    import onnxruntime as ort  # present: the session was made

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

    sr = _load_onnx_superres(package, package.superres) if superres and package.superres else None
    return LoadedEncoder(package, "onnx", run, f"{path.name} (onnxruntime {ort.__version__}, CPU)", sr)


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


def _torch_superres(
    ckpt: Mapping[str, Any], student: Mapping[str, Any] | None, train_cfg: Mapping[str, Any], p: Path
) -> tuple[Any, Any] | None:
    """``(SuperresConfig, state dict)`` of a checkpoint's trained SR, or None when it has none: the
    ``superres`` entry of ``lp3d.training.export --weights`` files, or a paper-recipe training checkpoint's
    student SR (the CPU recipe's student carries an SR module it never trains: not used)."""
    from lp3d.nets.superres import SuperresConfig

    if ckpt.get("superres") is not None:
        entry = ckpt["superres"]
        if not isinstance(entry, Mapping) or not isinstance(entry.get("state"), Mapping):
            raise ModelPackageError(
                f"{p}: 'superres' must be {{'config': SuperresConfig dict, 'state': state dict}}"
            )
        raw, state = entry.get("config"), dict(entry["state"])
    elif student is not None and train_cfg.get("recipe", "paper") == "paper" and "superres" in train_cfg:
        raw, state = train_cfg["superres"], _strip(student, "superres.")
    else:
        return None
    try:
        config = SuperresConfig.from_dict(_as_mapping(raw, "superres config", p))
    except (TypeError, ValueError) as e:
        raise ModelPackageError(f"{p}: the super-resolution configuration cannot be read ({e})") from None
    return config, state


def _build_torch_superres(package: ModelPackage, found: tuple[Any, Any], p: Path) -> LoadedSuperres:
    import torch

    from lp3d.nets.superres import FoldedSuperResolution, SuperResolution

    config, state = found
    if config.in_channels != N_CHANNELS:
        raise ModelPackageError(
            f"{p}: the super-resolution network reads {config.in_channels} channels, not {N_CHANNELS}"
        )
    sr = SuperResolution(config)
    try:
        sr.load_state_dict({k: torch.as_tensor(v).float() for k, v in state.items()}, strict=True)
    except RuntimeError as e:
        first = str(e).splitlines()[0]
        raise ModelPackageError(
            f"{p}: super-resolution weights do not fit their configuration: {first}"
        ) from None
    folded = FoldedSuperResolution(sr.eval()).eval()

    def run(features: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return folded(torch.from_numpy(features)).float().numpy()

    return LoadedSuperres(
        package,
        "torch",
        config.input_resolution,
        config.output_resolution,
        config.in_channels,
        f"{p.name} super-resolution (torch {torch.__version__}, CPU)",
        run,
    )


def _load_torch(path: Path, *, superres: bool = False) -> LoadedEncoder:
    try:
        import torch
    except ImportError as e:
        raise ModelPackageError(f"the torch backend needs PyTorch: {e}") from None
    from lp3d.nets.encoder import EncoderConfig, build_encoder

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
    train_cfg: dict[str, Any] = {}
    if isinstance(cfg_dict.get("encoder"), Mapping):
        train_cfg = cfg_dict
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

    sr = None
    if superres:
        found = _torch_superres(ckpt, student, train_cfg, p)
        sr = _build_torch_superres(package, found, p) if found is not None else None
    return LoadedEncoder(package, "torch", run, f"{p.name} (torch {torch.__version__}, CPU)", sr)


def load_encoder(
    path: str | os.PathLike[str], backend: Backend | None = None, *, superres: bool = False
) -> LoadedEncoder:
    """Load an encoder; ``backend`` None picks ``torch`` for ``.pt``/``.pth``/folders, else ``onnx``.
    With ``superres`` the package's super-resolution network is loaded too (``.superres``, None when
    the package has none).

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` (a ValueError) with a clear message for a
    missing file or sidecar, an unreadable model, or a layout that does not fit.
    """
    p = Path(path)
    if backend is None:
        backend = "torch" if p.suffix.lower() in (".pt", ".pth") or p.is_dir() else "onnx"
    if backend == "onnx":
        if p.suffix.lower() in (".pt", ".pth"):
            raise ModelPackageError(f"{p}: a torch checkpoint; use --backend torch (or export it to ONNX)")
        return _load_onnx(p, superres=superres)
    if backend == "torch":
        if p.suffix.lower() == ".onnx":
            raise ModelPackageError(f"{p}: an ONNX model; use --backend onnx")
        return _load_torch(p, superres=superres)
    raise ModelPackageError(f"unknown backend {backend!r} (use onnx or torch)")


def load_superres(
    path: str | os.PathLike[str] | None = None, backend: Backend | None = None
) -> LoadedSuperres | None:
    """The super-resolution network of the model package ``path`` (default: the shipped model), or
    None when the package has none. ``backend`` as for :func:`load_encoder`. An ONNX package's encoder
    file is not loaded; a torch checkpoint is read whole.

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` for a package or SR file that is missing,
    altered (SHA-256) or does not fit its sidecar entry.
    """
    p = Path(path) if path is not None else DEFAULT_MODEL
    if backend is None:
        backend = "torch" if p.suffix.lower() in (".pt", ".pth") or p.is_dir() else "onnx"
    if backend == "onnx" and p.suffix.lower() not in (".pt", ".pth"):
        package = load_model_package(p)
        return _load_onnx_superres(package, package.superres) if package.superres is not None else None
    return load_encoder(p, backend, superres=True).superres


def superresolve(
    features: np.ndarray, *, model: str | os.PathLike[str] | None = None, backend: Backend | None = None
) -> np.ndarray:
    """One call from a raw feature render to the final image: ``features`` (B, 32, R, R) or (32, R, R)
    float32 (the renderer's ``features`` output at the network's ``input_resolution``) -> image
    (B, 3, R_out, R_out) or (3, R_out, R_out) in about [-1, 1], with the super-resolution network of
    ``model`` (default: the shipped model). Loads the network on every call: keep the result of
    :func:`load_superres` to run it many times.

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` when the package has no such network.
    """
    sr = load_superres(model, backend)
    if sr is None:
        where = Path(model) if model is not None else DEFAULT_MODEL
        raise ModelPackageError(
            f"{where}: the model package has no super-resolution network (its sidecar has no 'superres'); "
            "render the raw image instead, or fit one with python -m lp3d.training.superres_fit"
        )
    return sr(features)
