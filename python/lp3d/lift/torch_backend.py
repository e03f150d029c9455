"""The ``torch`` backend of :func:`lp3d.lift.inference.load_encoder`: a plain state-dict checkpoint
(``torch.load(weights_only=True)``, never unpickling code) in either layout the inference module's
docstring describes, its decoder and bounds from the checkpoint or the ``.json`` sidecar beside it,
and its super-resolution network when it has one.

May import :mod:`lp3d.lift.model_package`, :mod:`lp3d.lift.loaded`, :mod:`lp3d.nets` and
:mod:`lp3d.render`; torch only when a checkpoint is loaded."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.lift.loaded import LoadedEncoder, LoadedSuperres, _reshape_planes
from lp3d.lift.model_package import ModelPackage, ModelPackageError, load_model_package, sidecar_path
from lp3d.lift.sidecar import _DECODER_SHAPES, _check_decoder_range, _check_sizes, _parse_json
from lp3d.render.settings import N_CHANNELS


def _as_mapping(value: Any, what: str, where: Path) -> dict[str, Any]:
    """A dict from a dict or a JSON string (checkpoints store configs either way)."""
    if isinstance(value, str):
        value = _parse_json(where, value, f"{what} (JSON)")
    if not isinstance(value, Mapping):
        raise ModelPackageError(f"{where}: {what} must be a dict, got {type(value).__name__}")
    return dict(value)


def _strip(state: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    return {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}


def _state_dict(value: Any, what: str, where: Path) -> dict[str, Any]:
    """A state dict from a checkpoint: a mapping of string names to tensors (a file from someone else
    may hold anything there: integer keys, lists, None)."""
    import torch

    if not isinstance(value, Mapping):
        raise ModelPackageError(f"{where}: {what} must be a state dict, got {type(value).__name__}")
    for key, tensor in value.items():
        if not isinstance(key, str):
            raise ModelPackageError(
                f"{where}: {what} must map parameter names to tensors; it has the key {key!r} "
                f"({type(key).__name__})"
            )
        if not isinstance(tensor, torch.Tensor):
            raise ModelPackageError(f"{where}: {what}[{key!r}] must be a tensor, got {type(tensor).__name__}")
    return dict(value)


def _load_weights(build: Callable[[], Any], state: Mapping[str, Any], what: str, where: Path) -> Any:
    """``build()`` with the weights ``state``, checked first against a copy built on the meta device
    (shapes only, no memory): a configuration that claims sizes its weights do not have is refused
    before it allocates anything."""
    import torch

    with torch.device("meta"):
        shapes = {k: tuple(v.shape) for k, v in build().state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    if shapes != got:
        missing, extra = sorted(shapes.keys() - got.keys()), sorted(got.keys() - shapes.keys())
        wrong = sorted(k for k in shapes.keys() & got.keys() if shapes[k] != got[k])
        first = (
            f"{wrong[0]!r} has shape {got[wrong[0]]} in the file, {shapes[wrong[0]]} in the configuration"
            if wrong
            else f"{len(missing)} missing (e.g. {missing[:1]}), {len(extra)} unexpected (e.g. {extra[:1]})"
        )
        raise ModelPackageError(f"{where}: {what} do not fit their configuration: {first}")
    module = build()
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).splitlines()[0]
        raise ModelPackageError(f"{where}: {what} do not fit their configuration: {first}") from None
    return module.eval()


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
        raw, state = entry.get("config"), _state_dict(entry["state"], "'superres.state'", p)
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
    state = {k: v.float() for k, v in state.items()}
    sr = _load_weights(lambda: SuperResolution(config), state, "super-resolution weights", p)
    folded = FoldedSuperResolution(sr).eval()

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


def _read_checkpoint(p: Path) -> Mapping[str, Any]:
    """The checkpoint at ``p`` as a dict, read with ``weights_only=True`` (no code is unpickled)."""
    import torch

    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for non-checkpoints (UnpicklingError, RuntimeError, ...)
        raise ModelPackageError(f"{p}: cannot be read as a plain state-dict checkpoint ({e})") from None
    if not isinstance(ckpt, Mapping):
        raise ModelPackageError(f"{p}: a checkpoint must hold a dict, got {type(ckpt).__name__}")
    return ckpt


def _encoder_config(ckpt: Mapping[str, Any], p: Path, layout_hint: str) -> tuple[Any, dict[str, Any]]:
    """``(EncoderConfig, training config dict or {})`` of a checkpoint."""
    from lp3d.nets.encoder import EncoderConfig

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
    _check_sizes(str(p), config.image_size, config.triplane_resolution)
    return config, train_cfg


def _decoder_and_bounds(
    ckpt: Mapping[str, Any], student: Mapping[str, Any] | None, p: Path
) -> tuple[dict[str, Any] | None, dict[str, Any] | None, Path, ModelPackage | None]:
    """``(decoder, bounds, sidecar path, sidecar)``: the decoder weights and scene bounds the checkpoint
    carries (None where it has none) and the ``.json`` sidecar beside it, read when one is missing."""
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
    return decoder, bounds, side, sidecar


def _torch_encoder(config: Any, state: Mapping[str, Any], p: Path) -> Any:
    """The encoder of ``config`` with the weights ``state``, in eval mode."""
    from lp3d.nets.encoder import build_encoder

    return _load_weights(lambda: build_encoder(config), state, f"encoder weights (config {config.name!r})", p)


def _torch_package(
    config: Any,
    p: Path,
    side: Path,
    decoder: Mapping[str, Any] | None,
    bounds: Mapping[str, Any] | None,
    sidecar: ModelPackage | None,
) -> ModelPackage:
    """The :class:`ModelPackage` of a checkpoint: its decoder and bounds, or the sidecar's, checked."""

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
    if all(a.shape == want for a, want in zip((w0, b0, w1, b1), _DECODER_SHAPES.values(), strict=True)):
        _check_decoder_range(str(p), (w0, b0, w1, b1))  # other shapes: named by the check below
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
    return package


def _plane_offset(offset: Any, config: Any, p: Path) -> Any:
    """A training checkpoint's mean triplane (3, 32, T, T), float32 and finite."""
    import torch

    want = (3, N_CHANNELS, config.triplane_resolution, config.triplane_resolution)
    if not isinstance(offset, torch.Tensor) or tuple(offset.shape) != want:
        got = tuple(offset.shape) if isinstance(offset, torch.Tensor) else type(offset).__name__
        raise ModelPackageError(f"{p}: 'plane_offset' must be a {want} tensor, got {got}")
    offset = offset.float()
    if not bool(torch.isfinite(offset).all()):
        raise ModelPackageError(f"{p}: 'plane_offset' contains NaN/Inf")
    return offset


def _load_torch(path: Path, *, superres: bool = False) -> LoadedEncoder:
    try:
        import torch
    except ImportError as e:
        raise ModelPackageError(f"the torch backend needs PyTorch: {e}") from None

    p = _checkpoint_file(path)
    ckpt = _read_checkpoint(p)
    layout_hint = (
        f"{p}: checkpoint layout not understood (keys {sorted(map(str, ckpt))[:12]}); expected "
        "{'config': EncoderConfig dict, 'encoder': state dict, 'decoder': {w0, b0, w1, b1}, "
        "'bounds': {box_warp, ray_start, ray_end}} or a python -m lp3d.train checkpoint"
    )
    config, train_cfg = _encoder_config(ckpt, p, layout_hint)
    # The encoder's weights, and the decoder's where the checkpoint has them.
    student = _state_dict(ckpt["student"], "'student'", p) if "student" in ckpt else None
    if isinstance(ckpt.get("encoder"), Mapping):
        state = _state_dict(ckpt["encoder"], "'encoder'", p)
    elif student is not None:
        state = _strip(student, "encoder.")
    else:
        raise ModelPackageError(layout_hint)
    # A training checkpoint's student may add a learned mean triplane to the encoder's output.
    offset = student.get("plane_offset") if student is not None else ckpt.get("plane_offset")
    if offset is not None:
        offset = _plane_offset(offset, config, p)
    decoder, bounds, side, sidecar = _decoder_and_bounds(ckpt, student, p)
    package = _torch_package(config, p, side, decoder, bounds, sidecar)  # cheap checks first
    encoder = _torch_encoder(config, state, p)

    def run(images: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            out = encoder(torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)))
            if offset is not None:
                out = out + offset
        return _reshape_planes(out.float().numpy(), images.shape[0], str(p), config.triplane_resolution)

    sr = None
    if superres:
        found = _torch_superres(ckpt, student, train_cfg, p)
        sr = _build_torch_superres(package, found, p) if found is not None else None
    return LoadedEncoder(package, "torch", run, f"{p.name} (torch {torch.__version__}, CPU)", sr)
