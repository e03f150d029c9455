"""The ``torch`` backend of :func:`lp3d.lift.inference.load_encoder`: a plain state-dict checkpoint
(``torch.load(weights_only=True)``, never unpickling code) in either layout the inference module's
docstring describes, its decoder and bounds from the checkpoint or the ``.json`` sidecar beside it,
and its super-resolution network when it has one.

May import :mod:`lp3d.lift.model_package`, :mod:`lp3d.lift.loaded`, :mod:`lp3d.nets` and
:mod:`lp3d.render`; torch only when a checkpoint is loaded."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.lift.loaded import LoadedEncoder, LoadedSuperres, reshape_planes
from lp3d.lift.model_package import ModelPackage, ModelPackageError, load_model_package, sidecar_path
from lp3d.lift.run_checkpoints import newest_readable
from lp3d.lift.sidecar import (
    DECODER_SHAPES,
    as_float32,
    check_decoder_array,
    check_decoder_range,
    check_sizes,
    parse_json,
    short_repr,
    short_text,
)
from lp3d.render.npz_reader import read_torch_file
from lp3d.render.settings import N_CHANNELS


def _as_mapping(value: Any, what: str, where: Path) -> dict[str, Any]:
    """A dict from a dict or a JSON string (checkpoints store configs either way)."""
    if isinstance(value, str):
        value = parse_json(where, value, f"{what} (JSON)")
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
                f"{where}: {what} must map parameter names to tensors; it has the key {short_repr(key)} "
                f"({type(key).__name__})"
            )
        if not isinstance(tensor, torch.Tensor):
            raise ModelPackageError(
                f"{where}: {what}[{short_repr(key)}] must be a tensor, got {type(tensor).__name__}"
            )
        if tensor.is_complex():  # loading would drop the imaginary part with only a warning
            raise ModelPackageError(f"{where}: {what}[{short_repr(key)}] must be real, got {tensor.dtype}")
    return dict(value)


def _layers(config: Any) -> int:
    """How many layers a configuration asks to be built: its depths (``*_depth``, ``*_depths``,
    ``*_convs``) and the lengths of its lists (one stage or branch each). Each builds at least one
    tensor, so a file with fewer tensors cannot fit it."""
    total = 0
    for name, value in config.to_dict().items():
        counts = name.endswith(("_depth", "_depths", "_convs"))
        if isinstance(value, list):
            total += len(value) + (sum(value) if counts else 0)
        elif counts and isinstance(value, int):
            total += value
    return total


def _skip_normal_init() -> Any:
    """A mode that skips the normal initialisers while a network is built on the meta device: ``normal_``
    has no meta kernel, and its Python reference imports torch._dynamo (slow on the first load of a
    process); a meta tensor's values are never read."""
    import torch
    from torch.overrides import TorchFunctionMode

    skipped = {torch.Tensor.normal_, torch.nn.init.normal_, torch.nn.init.trunc_normal_}

    class SkipNormal(TorchFunctionMode):
        def __torch_function__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            if func in skipped:  # nn.init's functions are called with the tensor as a keyword
                return args[0] if args else (kwargs or {}).get("tensor")
            return func(*args, **(kwargs or {}))

    return SkipNormal()


def _load_weights(
    build: Callable[[], Any], config: Any, state: Mapping[str, Any], what: str, where: Path
) -> Any:
    """``build()`` with the weights ``state``, checked first against a copy built on the meta device
    (shapes only, no memory): a configuration that claims sizes its weights do not have is refused
    before it allocates anything, and one that claims more layers than the file has tensors (2^63
    convolutions) before it is built at all."""
    import torch

    layers = _layers(config)
    if layers > len(state):
        raise ModelPackageError(
            f"{where}: {what} do not fit their configuration: it asks for {short_repr(layers)} layers, "
            f"the file has {len(state)} tensors"
        )
    try:
        with torch.device("meta"), _skip_normal_init():
            shapes = {k: tuple(v.shape) for k, v in build().state_dict().items()}
    except (ArithmeticError, RuntimeError, TypeError, ValueError) as e:
        raise ModelPackageError(
            f"{where}: {what}: the configuration cannot be built ({short_text(e)})"
        ) from None
    got = {k: tuple(v.shape) for k, v in state.items()}
    if shapes != got:
        missing, extra = sorted(shapes.keys() - got.keys()), sorted(got.keys() - shapes.keys())
        wrong = sorted(k for k in shapes.keys() & got.keys() if shapes[k] != got[k])
        first = (
            f"{short_repr(wrong[0])} has shape {got[wrong[0]]} in the file, {shapes[wrong[0]]} in the "
            "configuration"
            if wrong
            else f"{len(missing)} missing (e.g. {short_repr(missing[:1])}), {len(extra)} unexpected "
            f"(e.g. {short_repr(extra[:1])})"
        )
        raise ModelPackageError(f"{where}: {what} do not fit their configuration: {first}")
    module = build()
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = short_text(str(e).splitlines()[0])
        raise ModelPackageError(f"{where}: {what} do not fit their configuration: {first}") from None
    return module.eval()


def _checkpoint_of(path: Path) -> tuple[Path, Mapping[str, Any]]:
    """``(file, checkpoint)``: the checkpoint file at ``path``, or for a training run folder its newest
    readable ``checkpoints/step-*.pt`` (:func:`lp3d.lift.run_checkpoints.newest_readable`, the rule
    ``lp3d eval`` and ``--resume`` follow: steps parsed from the names, damaged files skipped)."""
    if path.is_dir():
        return newest_readable(path, lambda f: (f, _read_checkpoint(f)), ModelPackageError)
    if not path.is_file():
        raise ModelPackageError(f"{path}: no such checkpoint file")
    return path, _read_checkpoint(path)


def _torch_superres(
    ckpt: Mapping[str, Any], student: Mapping[str, Any] | None, train_cfg: Mapping[str, Any], p: Path
) -> tuple[Any, Any] | None:
    """``(SuperresConfig, state dict)`` of a checkpoint's trained SR, or None when it has none: the
    ``superres`` entry of ``lp3d export --weights`` files, or a paper-recipe training checkpoint's
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
        raise ModelPackageError(
            f"{p}: the super-resolution configuration cannot be read ({short_text(e)})"
        ) from None
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
    sr = _load_weights(lambda: SuperResolution(config), config, state, "super-resolution weights", p)
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
        f"{p} (its super-resolution network)",
    )


def _read_checkpoint(p: Path) -> Mapping[str, Any]:
    """The checkpoint at ``p`` as a dict, read with ``weights_only=True`` (no code is unpickled)."""
    try:
        ckpt = read_torch_file(p, "a checkpoint or weights file")
    except (OSError, ValueError) as e:
        raise ModelPackageError(str(e)) from None
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
            f"{p}: the encoder configuration cannot be read by this version ({short_text(e)})"
        ) from None
    check_sizes(str(p), config.image_size, config.triplane_resolution)
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

    what = f"encoder weights (config {short_repr(config.name)})"
    return _load_weights(lambda: build_encoder(config), config, state, what, p)


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
        a = v.detach().cpu().numpy() if hasattr(v, "detach") else np.asarray(v)
        if np.iscomplexobj(a):
            raise TypeError(f"complex values ({a.dtype})")
        return a

    try:
        if decoder is not None:
            w0, b0, w1, b1 = (as_float32(f"{p}: decoder.{k}", array(decoder[k])) for k in DECODER_SHAPES)
        else:
            assert sidecar is not None
            w0, b0, w1, b1 = sidecar.decoder
        if bounds is not None:
            box_warp, ray_start, ray_end = (float(bounds[k]) for k in ("box_warp", "ray_start", "ray_end"))
        else:
            assert sidecar is not None
            box_warp, ray_start, ray_end = sidecar.box_warp, sidecar.ray_start, sidecar.ray_end
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        if isinstance(e, ModelPackageError):
            raise
        raise ModelPackageError(
            f"{p}: malformed decoder or bounds ({type(e).__name__}: {short_text(e)})"
        ) from None
    for name, arr in zip(DECODER_SHAPES, (w0, b0, w1, b1), strict=True):
        try:
            check_decoder_array(f"decoder.{name}", arr)  # shapes and NaN/Inf before the range
        except ModelPackageError as e:
            raise ModelPackageError(f"{p}: {e}") from None
    check_decoder_range(str(p), (w0, b0, w1, b1))
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
        raise ModelPackageError(f"{p}: bad decoder or bounds ({short_text(e)})") from None
    return package


def _plane_offset(offset: Any, config: Any, p: Path) -> Any:
    """A training checkpoint's mean triplane (3, 32, T, T), float32 and finite."""
    import torch

    want = (3, N_CHANNELS, config.triplane_resolution, config.triplane_resolution)
    if not isinstance(offset, torch.Tensor) or tuple(offset.shape) != want:
        got = tuple(offset.shape) if isinstance(offset, torch.Tensor) else type(offset).__name__
        raise ModelPackageError(f"{p}: 'plane_offset' must be a {want} tensor, got {got}")
    if offset.is_complex():
        raise ModelPackageError(f"{p}: 'plane_offset' must be real, got {offset.dtype}")
    offset = offset.float()
    if not bool(torch.isfinite(offset).all()):
        raise ModelPackageError(f"{p}: 'plane_offset' contains NaN/Inf")
    return offset


@dataclass(frozen=True)
class EncoderWeights:
    """What a model package or a training checkpoint holds of the encoder, checked
    (:func:`read_encoder_weights`)."""

    path: Path  # the file read (a run folder's newest readable checkpoint)
    checkpoint: Mapping[str, Any]
    config: Any  # EncoderConfig
    train_config: dict[str, Any]  # a training checkpoint's config, {} for a package
    student: dict[str, Any] | None  # a training checkpoint's student state
    state: dict[str, Any]  # the encoder's state dict, names without a prefix
    offset: Any  # the (3, 32, T, T) mean triplane added to the encoder's output, or None


def read_encoder_weights(path: Path) -> EncoderWeights:
    """The encoder's configuration, weights and plane offset of a model package ``.pt`` or a
    ``python -m lp3d.train`` checkpoint (or run folder), read with ``weights_only=True``; raises
    :class:`ModelPackageError` naming what is missing or malformed. Used to load a model and to start
    a training run from one (``--init-from``)."""
    p, ckpt = _checkpoint_of(Path(path))
    keys = sorted(short_repr(k, 40) for k in ckpt)[:12]  # any key: str() fails on a 5,000-digit int
    layout_hint = (
        f"{p}: checkpoint layout not understood (keys {', '.join(keys)}); expected "
        "{'config': EncoderConfig dict, 'encoder': state dict, 'decoder': {w0, b0, w1, b1}, "
        "'bounds': {box_warp, ray_start, ray_end}} or a python -m lp3d.train checkpoint"
    )
    config, train_cfg = _encoder_config(ckpt, p, layout_hint)
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
    return EncoderWeights(p, ckpt, config, train_cfg, student, state, offset)


def load_torch_encoder(path: Path, *, superres: bool = False) -> LoadedEncoder:
    """The ``torch`` backend of :func:`lp3d.lift.inference.load_encoder`: a state-dict checkpoint."""
    try:
        import torch
    except ImportError as e:
        raise ModelPackageError(f"the torch backend needs PyTorch: {e}") from None

    w = read_encoder_weights(path)
    p, ckpt, config, student, state, offset = w.path, w.checkpoint, w.config, w.student, w.state, w.offset
    train_cfg = w.train_config
    decoder, bounds, side, sidecar = _decoder_and_bounds(ckpt, student, p)
    package = _torch_package(config, p, side, decoder, bounds, sidecar)  # cheap checks first
    encoder = _torch_encoder(config, state, p)

    def run(images: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            out = encoder(torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)))
            if offset is not None:
                out = out + offset
        return reshape_planes(out.float().numpy(), images.shape[0], str(p), config.triplane_resolution)

    sr = None
    if superres:
        found = _torch_superres(ckpt, student, train_cfg, p)
        sr = _build_torch_superres(package, found, p) if found is not None else None
    return LoadedEncoder(package, "torch", run, f"{p.name} (torch {torch.__version__}, CPU)", sr)
