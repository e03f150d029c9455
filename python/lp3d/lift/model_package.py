"""The model package: an exported encoder (``MODEL.onnx``) plus a small JSON sidecar (``MODEL.json``).

An encoder alone maps an image to triplane *planes*; a usable triplane file also needs the decoder
the encoder was trained with and the scene bounds. The sidecar carries exactly that, as plain JSON
(no pickle, readable by any language). Spec: ``docs/model-package.md``. In short::

    {
      "format": "lp3d-model-package", "format_version": 1,
      "model": "small.onnx",                     # the encoder file, relative to the sidecar
      "config_name": "small",                    # EncoderConfig name
      "image_size": 256,                         # encoder input side S: (B, 3, S, S) in [-1, 1]
      "triplane_resolution": 128,                # output (B, 3, 32, T, T)
      "box_warp": 1.0, "ray_start": 2.25, "ray_end": 3.3,
      "decoder": {"w0": [[...]], "b0": [...], "w1": [[...]], "b1": [...]},   # effective weights
      "encoder_config": {...},                   # optional: the full EncoderConfig.to_dict()
      "input_name": "image", "output_name": "planes",  # optional ONNX tensor names
      "superres": {                              # optional: the super-resolution network
        "model": "small.superres.onnx",          # features (B, 32, R, R) -> image (B, 3, R_out, R_out)
        "input_resolution": 64, "output_resolution": 256, "in_channels": 32,
        "sha256": "...",                         # of the .onnx file, checked when it is loaded
        "about": {...}                           # optional: how it was made, its held-out scores
      }
    }

:func:`save_model_package` writes the sidecar (atomically) next to an ``.onnx`` file;
:func:`load_model_package` reads it back, given either the ``.onnx`` or the ``.json`` path;
:func:`set_package_superres` adds (or replaces) the super-resolution entry of an existing sidecar.
The format constants, :class:`ModelPackageError` and the checks of each field are in
:mod:`lp3d.lift.sidecar` (and importable from here).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.array_cache import file_sha256
from lp3d.atomic import atomic_path
from lp3d.lift.sidecar import (
    DECODER_SHAPES,
    PACKAGE_FORMAT,
    PACKAGE_FORMAT_VERSION,
    ModelPackageError,
    SuperresEntry,
    check_decoder_array,
    check_decoder_range,
    check_scene_bounds,
    check_sizes,
    parse_superres,
    read_sidecar,
    short_repr,
    sidecar_decoder,
    sidecar_field,
    sidecar_number,
    verify_superres_file,
    verify_superres_weights,
)
from lp3d.render.settings import N_CHANNELS, SceneBounds
from lp3d.render.triplane import TriplaneData

__all__ = [
    "PACKAGE_FORMAT",
    "PACKAGE_FORMAT_VERSION",
    "ModelPackage",
    "ModelPackageError",
    "SuperresEntry",
    "decoder_digest",
    "file_sha256",
    "load_model_package",
    "save_model_package",
    "set_package_superres",
    "sidecar_path",
    "superres_entry",
    "superres_path",
    "verify_superres_file",
    "verify_superres_weights",
]


@dataclass(frozen=True, eq=False)
class ModelPackage:
    """A loaded sidecar: where the encoder is, what it expects and what to put in its triplanes.

    ``model_path`` is the encoder file (it may not exist; callers check when they load it), ``w0``
    (64, 32), ``b0`` (64,), ``w1`` (33, 64), ``b1`` (33,) are the decoder's effective weights (float32).
    """

    sidecar: Path
    model_path: Path
    config_name: str
    image_size: int
    triplane_resolution: int
    box_warp: float
    ray_start: float
    ray_end: float
    w0: np.ndarray
    b0: np.ndarray
    w1: np.ndarray
    b1: np.ndarray
    encoder_config: dict[str, Any] | None = None
    input_name: str | None = None
    output_name: str | None = None
    superres: SuperresEntry | None = None

    @property
    def decoder(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(w0, b0, w1, b1)``."""
        return self.w0, self.b0, self.w1, self.b1

    def triplane(
        self, planes: np.ndarray, *, source: str | None = None, camera: np.ndarray | None = None
    ) -> TriplaneData:
        """A self-contained triplane from encoder planes (3, 32, T, T) and this package's decoder/bounds.
        Planes that this decoder would take past float32 (which the renderer refuses) are refused here,
        before the triplane is written."""
        peak = float(np.max(np.abs(planes))) if np.size(planes) else 0.0
        if np.isfinite(peak):  # NaN/Inf planes: TriplaneData names them
            check_decoder_range(str(self.model_path), self.decoder, peak)
        return TriplaneData(
            planes=planes,
            w0=self.w0,
            b0=self.b0,
            w1=self.w1,
            b1=self.b1,
            box_warp=self.box_warp,
            ray_start=self.ray_start,
            ray_end=self.ray_end,
            camera=camera,
            source=source,
        )


def sidecar_path(model_path: str | os.PathLike[str]) -> Path:
    """The sidecar of ``MODEL.onnx`` (or any model file): ``MODEL.json`` in the same folder."""
    return Path(model_path).with_suffix(".json")


def superres_path(model_path: str | os.PathLike[str]) -> Path:
    """Where ``lp3d export`` writes the super-resolution network of ``MODEL.onnx``:
    ``MODEL.superres.onnx``."""
    p = Path(model_path)
    return p.with_name(p.with_suffix("").name + ".superres.onnx")


def decoder_digest(decoder: Any) -> str:
    """SHA-256 of the decoder's effective weights as float32 (w0, b0, w1, b1 in that order): names the
    feature space a super-resolution network was fit on."""
    h = hashlib.sha256()
    for arr in _decoder_arrays(decoder).values():
        h.update(np.ascontiguousarray(arr, dtype="<f4").tobytes())
    return h.hexdigest()


# ------------------------------------------------------------------------------------------ writing


def _decoder_arrays(decoder: Any) -> dict[str, np.ndarray]:
    """``{"w0", "b0", "w1", "b1"}`` float32 arrays from a 4-sequence, a mapping or an object with attributes.

    Torch tensors (e.g. ``TriplaneDecoder.weights()``) are accepted through ``detach().cpu().numpy()``.
    """
    if isinstance(decoder, Mapping):
        values = [decoder.get(k) for k in DECODER_SHAPES]
    elif all(hasattr(decoder, k) for k in DECODER_SHAPES):
        values = [getattr(decoder, k) for k in DECODER_SHAPES]
    elif isinstance(decoder, Sequence) and len(decoder) == 4:
        values = list(decoder)
    else:
        raise ModelPackageError(
            "decoder must be (w0, b0, w1, b1), a mapping with those keys or an object with those attributes"
        )
    out: dict[str, np.ndarray] = {}
    for name, value in zip(DECODER_SHAPES, values, strict=True):
        if value is None:
            raise ModelPackageError(f"decoder.{name}: missing")
        if hasattr(value, "detach"):  # a torch tensor, without importing torch here
            value = value.detach().cpu().numpy()
        arr = np.asarray(value, dtype=np.float32)
        check_decoder_array(f"decoder.{name}", arr)
        out[name] = arr
    return out


def _bounds_of(bounds: Any) -> tuple[float, float, float]:
    """``(box_warp, ray_start, ray_end)``, checked, from what :meth:`SceneBounds.of` reads (a
    ``SceneBounds``, a triplane, a mapping) or a 3-sequence."""
    try:
        if isinstance(bounds, Sequence) and not isinstance(bounds, str) and len(bounds) == 3:
            scene = SceneBounds(*(float(v) for v in bounds))
        else:
            scene = SceneBounds.of(bounds)
    except (AttributeError, KeyError, TypeError, ValueError) as e:
        raise ModelPackageError(f"bounds must have box_warp, ray_start and ray_end as numbers: {e}") from None
    check_scene_bounds("bounds", scene.box_warp, scene.ray_start, scene.ray_end)
    return scene.box_warp, scene.ray_start, scene.ray_end


def _config_dict(config: Any) -> dict[str, Any]:
    """The EncoderConfig as a dict: from an EncoderConfig, a dict, or a config name."""
    if isinstance(config, str):
        from lp3d.nets.encoder import EncoderConfig  # torch is only needed for a name

        try:
            return EncoderConfig.named(config).to_dict()
        except ValueError as e:
            raise ModelPackageError(str(e)) from None
    if hasattr(config, "to_dict"):
        return dict(config.to_dict())
    if isinstance(config, Mapping):
        return dict(config)
    raise ModelPackageError(f"config must be an EncoderConfig, a dict or a name, got {type(config).__name__}")


def save_model_package(
    onnx_path: str | os.PathLike[str],
    decoder: Any,
    config: Any,
    bounds: Any,
    *,
    input_name: str | None = "image",
    output_name: str | None = "planes",
    superres: Mapping[str, Any] | None = None,
) -> Path:
    """Write the sidecar ``MODEL.json`` next to ``onnx_path`` (the ``.onnx`` need not exist yet).

    Args:
        onnx_path: the exported encoder, e.g. ``python/lp3d/models/small.onnx``.
        decoder: effective decoder weights ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` (numpy or
            torch), a mapping with those keys, or an object with those attributes (e.g. a TriplaneData).
        config: the encoder's :class:`~lp3d.nets.encoder.EncoderConfig` (or its dict, or a config name).
        bounds: ``box_warp``, ``ray_start``, ``ray_end`` (``lp3d.training.SceneBounds``, a dict, a tuple).
        input_name / output_name: the ONNX graph's tensor names (informational; None to omit).
        superres: the ``superres`` entry (:func:`superres_entry`), or None for a package without one.

    Returns the sidecar path. Raises :class:`ModelPackageError` on bad values; the write is atomic.
    """
    onnx_path = Path(onnx_path)
    arrays = _decoder_arrays(decoder)
    box_warp, ray_start, ray_end = _bounds_of(bounds)
    cfg = _config_dict(config)
    try:
        image_size = int(cfg["image_size"])
        triplane_resolution = int(cfg["triplane_resolution"])
    except (KeyError, TypeError, ValueError) as e:
        raise ModelPackageError(f"config needs image_size and triplane_resolution: {e}") from None
    check_sizes("config", image_size, triplane_resolution)
    check_decoder_range("decoder", tuple(arrays.values()))
    data: dict[str, Any] = {
        "format": PACKAGE_FORMAT,
        "format_version": PACKAGE_FORMAT_VERSION,
        "model": onnx_path.name,
        "config_name": str(cfg.get("name", "custom")),
        "image_size": image_size,
        "triplane_resolution": triplane_resolution,
        "box_warp": box_warp,
        "ray_start": ray_start,
        "ray_end": ray_end,
        # float32 -> float64 is exact and JSON prints the shortest round-tripping repr: lossless.
        "decoder": {k: v.astype(np.float64).tolist() for k, v in arrays.items()},
        "encoder_config": cfg,
    }
    if input_name is not None:
        data["input_name"] = input_name
    if output_name is not None:
        data["output_name"] = output_name
    path = sidecar_path(onnx_path)
    if superres is not None:
        parse_superres(str(path), dict(superres), path.parent)
        data["superres"] = dict(superres)
    _write_sidecar(path, data)
    return path


def _write_sidecar(path: Path, data: dict[str, Any]) -> None:
    # The shared atomic writer: a temporary file of this call's own, with the usual permissions (a
    # model file is meant to be shared), synced and renamed; deleted on failure.
    with atomic_path(path, parents=False) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1)
        f.write("\n")


def superres_entry(
    onnx_path: str | os.PathLike[str],
    weights_path: str | os.PathLike[str],
    *,
    input_resolution: int,
    output_resolution: int,
    in_channels: int = N_CHANNELS,
    about: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The sidecar's ``superres`` object for an exported SR network at ``onnx_path`` and its folded
    weights at ``weights_path`` (:mod:`lp3d.lift.superres_weights`). Both must exist (their SHA-256
    are recorded) and sit beside the sidecar it goes into."""
    p, w = Path(onnx_path), Path(weights_path)
    for f in (p, w):
        if not f.is_file():
            raise ModelPackageError(f"{f}: no such super-resolution model file")
    if w.parent != p.parent:
        raise ModelPackageError(f"{w}: the weights file must sit beside {p}")
    entry: dict[str, Any] = {
        "model": p.name,
        "input_resolution": int(input_resolution),
        "output_resolution": int(output_resolution),
        "in_channels": int(in_channels),
        "sha256": file_sha256(p),
        "input_name": "features",
        "output_name": "image",
        "weights": w.name,
        "weights_sha256": file_sha256(w),
    }
    if about is not None:
        entry["about"] = json.loads(json.dumps(dict(about)))  # plain JSON values only
    parse_superres(str(p), entry, p.parent)
    return entry


def set_package_superres(path: str | os.PathLike[str], superres: Mapping[str, Any] | None) -> Path:
    """Add, replace (or with None remove) the ``superres`` entry of an existing package, given its
    ``.onnx`` or ``.json``; every other field is kept as it is. The sidecar is validated before and
    after, and rewritten atomically. Returns the sidecar path."""
    package = load_model_package(path)
    side = package.sidecar
    data = json.loads(side.read_text(encoding="utf-8"))
    if superres is None:
        data.pop("superres", None)
    else:
        parse_superres(str(side), dict(superres), side.parent)
        data["superres"] = dict(superres)
    _write_sidecar(side, data)
    load_model_package(side)
    return side


# ------------------------------------------------------------------------------------------ reading


def load_model_package(path: str | os.PathLike[str]) -> ModelPackage:
    """Read a model package given its ``.onnx`` (the sidecar beside it is read) or its ``.json``.

    Raises :class:`ModelPackageError` (a ValueError) naming the file and the field: no sidecar, not
    JSON, another format or version, missing or malformed fields, decoder shapes, NaN/Inf.
    """
    p = Path(path)
    side = p if p.suffix.lower() == ".json" else sidecar_path(p)
    data = read_sidecar(side)

    def field(name: str, kind: type | tuple[type, ...]) -> Any:
        return sidecar_field(side, data, name, kind)

    image_size = field("image_size", int)
    triplane_resolution = field("triplane_resolution", int)
    check_sizes(str(side), image_size, triplane_resolution)
    box_warp, ray_start, ray_end = (
        sidecar_number(side, data, k) for k in ("box_warp", "ray_start", "ray_end")
    )
    check_scene_bounds(str(side), box_warp, ray_start, ray_end)
    arrays = sidecar_decoder(side, field("decoder", dict))
    check_decoder_range(str(side), tuple(arrays.values()))
    model_name = field("model", str) if "model" in data else p.with_suffix(".onnx").name
    if Path(model_name).name != model_name:
        raise ModelPackageError(
            f"{side}: field 'model' must be a file name beside the sidecar, got {short_repr(model_name)}"
        )
    cfg = data.get("encoder_config")
    if cfg is not None and not isinstance(cfg, dict):
        raise ModelPackageError(f"{side}: field 'encoder_config' must be an object")
    superres = parse_superres(str(side), data["superres"], side.parent) if "superres" in data else None
    return ModelPackage(
        sidecar=side,
        model_path=p if p.suffix.lower() != ".json" else side.parent / model_name,
        config_name=str(data.get("config_name", "custom")),
        image_size=image_size,
        triplane_resolution=triplane_resolution,
        box_warp=box_warp,
        ray_start=ray_start,
        ray_end=ray_end,
        w0=arrays["w0"],
        b0=arrays["b0"],
        w1=arrays["w1"],
        b1=arrays["b1"],
        encoder_config=cfg,
        input_name=data.get("input_name") if isinstance(data.get("input_name"), str) else None,
        output_name=data.get("output_name") if isinstance(data.get("output_name"), str) else None,
        superres=superres,
    )
