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
      "input_name": "image", "output_name": "planes"   # optional ONNX tensor names
    }

:func:`save_model_package` writes the sidecar (atomically) next to an ``.onnx`` file;
:func:`load_model_package` reads it back, given either the ``.onnx`` or the ``.json`` path.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.atomic import atomic_path
from lp3d.settings import HIDDEN, N_CHANNELS, N_OUT
from lp3d.triplane import TriplaneData

__all__ = [
    "PACKAGE_FORMAT",
    "PACKAGE_FORMAT_VERSION",
    "ModelPackage",
    "ModelPackageError",
    "load_model_package",
    "save_model_package",
    "sidecar_path",
]

#: The ``format`` string every sidecar carries.
PACKAGE_FORMAT = "lp3d-model-package"
#: The only ``format_version`` this reader accepts (bump on incompatible changes).
PACKAGE_FORMAT_VERSION = 1

_DECODER_SHAPES: dict[str, tuple[int, ...]] = {
    "w0": (HIDDEN, N_CHANNELS),
    "b0": (HIDDEN,),
    "w1": (N_OUT, HIDDEN),
    "b1": (N_OUT,),
}


class ModelPackageError(ValueError):
    """A missing, unreadable or inconsistent model package; the message names the file and the field."""


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

    @property
    def decoder(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(w0, b0, w1, b1)``."""
        return self.w0, self.b0, self.w1, self.b1

    def triplane(
        self, planes: np.ndarray, *, source: str | None = None, camera: np.ndarray | None = None
    ) -> TriplaneData:
        """A self-contained triplane from encoder planes (3, 32, T, T) and this package's decoder/bounds."""
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


# ------------------------------------------------------------------------------------------ writing


def _decoder_arrays(decoder: Any) -> dict[str, np.ndarray]:
    """``{"w0", "b0", "w1", "b1"}`` float32 arrays from a 4-sequence, a mapping or an object with attributes.

    Torch tensors (e.g. ``TriplaneDecoder.weights()``) are accepted through ``detach().cpu().numpy()``.
    """
    if isinstance(decoder, Mapping):
        values = [decoder.get(k) for k in _DECODER_SHAPES]
    elif all(hasattr(decoder, k) for k in _DECODER_SHAPES):
        values = [getattr(decoder, k) for k in _DECODER_SHAPES]
    elif isinstance(decoder, Sequence) and len(decoder) == 4:
        values = list(decoder)
    else:
        raise ModelPackageError(
            "decoder must be (w0, b0, w1, b1), a mapping with those keys or an object with those attributes"
        )
    out: dict[str, np.ndarray] = {}
    for name, value in zip(_DECODER_SHAPES, values, strict=True):
        if value is None:
            raise ModelPackageError(f"decoder.{name}: missing")
        if hasattr(value, "detach"):  # a torch tensor, without importing torch here
            value = value.detach().cpu().numpy()
        arr = np.asarray(value, dtype=np.float32)
        _check_array(f"decoder.{name}", arr)
        out[name] = arr
    return out


def _check_array(where: str, arr: np.ndarray) -> None:
    name = where.rsplit(".", 1)[-1]
    if arr.shape != _DECODER_SHAPES[name]:
        raise ModelPackageError(f"{where}: shape must be {_DECODER_SHAPES[name]}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ModelPackageError(f"{where}: contains NaN/Inf")


def _bounds_of(bounds: Any) -> tuple[float, float, float]:
    """``(box_warp, ray_start, ray_end)`` from a mapping, an object with attributes or a 3-sequence."""
    keys = ("box_warp", "ray_start", "ray_end")
    if isinstance(bounds, Mapping):
        values = [bounds.get(k) for k in keys]
    elif all(hasattr(bounds, k) for k in keys):
        values = [getattr(bounds, k) for k in keys]
    elif isinstance(bounds, Sequence) and len(bounds) == 3:
        values = list(bounds)
    else:
        raise ModelPackageError("bounds must have box_warp, ray_start and ray_end")
    try:
        box_warp, ray_start, ray_end = (float(v) for v in values)  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise ModelPackageError(f"bounds must be numbers: {e}") from None
    _check_bounds("bounds", box_warp, ray_start, ray_end)
    return box_warp, ray_start, ray_end


def _check_bounds(where: str, box_warp: float, ray_start: float, ray_end: float) -> None:
    if not (math.isfinite(box_warp) and box_warp > 0):
        raise ModelPackageError(f"{where}: box_warp must be finite and > 0, got {box_warp!r}")
    if not (math.isfinite(ray_start) and ray_start >= 0):
        raise ModelPackageError(f"{where}: ray_start must be finite and >= 0, got {ray_start!r}")
    if not (math.isfinite(ray_end) and ray_end > ray_start):
        raise ModelPackageError(f"{where}: ray_end must be finite and > ray_start, got {ray_end!r}")


def _config_dict(config: Any) -> dict[str, Any]:
    """The EncoderConfig as a dict: from an EncoderConfig, a dict, or a config name."""
    if isinstance(config, str):
        from lp3d.encoder import EncoderConfig  # torch is only needed for a name

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
) -> Path:
    """Write the sidecar ``MODEL.json`` next to ``onnx_path`` (the ``.onnx`` need not exist yet).

    Args:
        onnx_path: the exported encoder, e.g. ``python/lp3d/models/small.onnx``.
        decoder: effective decoder weights ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` (numpy or
            torch), a mapping with those keys, or an object with those attributes (e.g. a TriplaneData).
        config: the encoder's :class:`~lp3d.encoder.EncoderConfig` (or its dict, or a config name).
        bounds: ``box_warp``, ``ray_start``, ``ray_end`` (e.g. ``lp3d.train.SceneBounds``, a dict, a tuple).
        input_name / output_name: the ONNX graph's tensor names (informational; None to omit).

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
    # The shared atomic writer: a temporary file of this call's own, with the usual permissions (a
    # model file is meant to be shared), synced and renamed; deleted on failure.
    with atomic_path(path, parents=False) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
    return path


# ------------------------------------------------------------------------------------------ reading


def load_model_package(path: str | os.PathLike[str]) -> ModelPackage:
    """Read a model package given its ``.onnx`` (the sidecar beside it is read) or its ``.json``.

    Raises :class:`ModelPackageError` (a ValueError) naming the file and the field: no sidecar, not
    JSON, another format or version, missing or malformed fields, decoder shapes, NaN/Inf.
    """
    p = Path(path)
    side = p if p.suffix.lower() == ".json" else sidecar_path(p)
    if not side.is_file():
        raise ModelPackageError(
            f"{side}: model package sidecar not found (a .onnx model needs its {side.name} beside it, "
            "written by lp3d.model_package.save_model_package; see docs/model-package.md)"
        )
    try:
        data = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ModelPackageError(f"{side}: unreadable model package sidecar ({e})") from None
    if not isinstance(data, dict) or data.get("format") != PACKAGE_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ModelPackageError(
            f"{side}: not an lp3d model package (format {got!r}, expected {PACKAGE_FORMAT!r})"
        )
    if data.get("format_version") != PACKAGE_FORMAT_VERSION:
        raise ModelPackageError(
            f"{side}: format_version {data.get('format_version')!r} is not supported "
            f"(this reader supports {PACKAGE_FORMAT_VERSION})"
        )

    def field(name: str, kind: type | tuple[type, ...]) -> Any:
        if name not in data:
            raise ModelPackageError(f"{side}: missing field {name!r}")
        value = data[name]
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ModelPackageError(f"{side}: field {name!r} has the wrong type ({type(value).__name__})")
        return value

    image_size = field("image_size", int)
    triplane_resolution = field("triplane_resolution", int)
    if image_size < 8 or triplane_resolution < 2:
        raise ModelPackageError(f"{side}: image_size/triplane_resolution out of range")
    box_warp, ray_start, ray_end = (
        float(field(k, (int, float))) for k in ("box_warp", "ray_start", "ray_end")
    )
    _check_bounds(str(side), box_warp, ray_start, ray_end)
    dec = field("decoder", dict)
    arrays: dict[str, np.ndarray] = {}
    for name in _DECODER_SHAPES:
        if name not in dec:
            raise ModelPackageError(f"{side}: decoder.{name} missing")
        try:
            arr = np.asarray(dec[name], dtype=np.float32)
        except (TypeError, ValueError) as e:
            raise ModelPackageError(f"{side}: decoder.{name} is not a numeric array ({e})") from None
        try:
            _check_array(f"decoder.{name}", arr)
        except ModelPackageError as e:
            raise ModelPackageError(f"{side}: {e}") from None
        arrays[name] = arr
    model_name = field("model", str) if "model" in data else p.with_suffix(".onnx").name
    if Path(model_name).name != model_name:
        raise ModelPackageError(
            f"{side}: field 'model' must be a file name beside the sidecar, got {model_name!r}"
        )
    cfg = data.get("encoder_config")
    if cfg is not None and not isinstance(cfg, dict):
        raise ModelPackageError(f"{side}: field 'encoder_config' must be an object")
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
    )
