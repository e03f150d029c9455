"""The model package's sidecar format and its checks: the format constants, :class:`ModelPackageError`
(what every check raises), the decoder's shapes, the scene bounds' ranges, the ``superres`` entry
(:class:`SuperresEntry`, its SHA-256 check) and the first steps of reading a sidecar (the JSON object
of this format and version, its typed fields, its decoder arrays). :mod:`lp3d.lift.model_package`
builds the package from them and re-exports the public names.

May import :mod:`lp3d.render` and the plumbing modules (:mod:`lp3d.array_cache`)."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.array_cache import file_sha256
from lp3d.render.settings import HIDDEN, N_CHANNELS, N_OUT, SceneBounds
from lp3d.render.triplane_io import MAX_PLANE_SIZE

#: The ``format`` string every sidecar carries.
PACKAGE_FORMAT = "lp3d-model-package"
#: The only ``format_version`` this reader accepts (bump on incompatible changes).
PACKAGE_FORMAT_VERSION = 1

#: The decoder's arrays (``w0, b0, w1, b1``, in this order) and their shapes.
DECODER_SHAPES: dict[str, tuple[int, ...]] = {
    "w0": (HIDDEN, N_CHANNELS),
    "b0": (HIDDEN,),
    "w1": (N_OUT, HIDDEN),
    "b1": (N_OUT,),
}


#: Caps on what a package may claim, checked before anything is allocated from a claim (a package
#: is outside input, like a triplane file: docs/reliability.md). A sidecar is a few hundred KiB.
MAX_SIDECAR_BYTES = 16 << 20
#: The encoder's input side S: photos are cropped to (3, S, S) float32 before the model runs.
MAX_IMAGE_SIZE = 4096
#: The triplane side T: the triplane files' own cap (``FILE_LIMITS``).
MAX_TRIPLANE_RESOLUTION = MAX_PLANE_SIZE
#: float32's largest value; a decoder whose sums could pass it renders Inf/NaN.
F32_MAX = float(np.finfo(np.float32).max)


class ModelPackageError(ValueError):
    """A missing, unreadable or inconsistent model package; the message names the file and the field."""


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)`` for an error message, cut to about ``limit`` characters: a value from a package is
    outside input (a 16 MiB string, a 4,300-digit integer) and an error stays one short line."""
    try:
        text = repr(value)
    except ValueError:  # an int of more than 4,300 digits (a pickle may hold one) has no repr
        return f"an integer of {value.bit_length()} bits"
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def short_text(text: object, limit: int = 400) -> str:
    """A library's error message (which may quote the input) cut to about ``limit`` characters."""
    s = str(text)
    return s if len(s) <= limit else f"{s[:limit]}... ({len(s)} characters)"


@dataclass(frozen=True)
class SuperresEntry:
    """A package's super-resolution network (the sidecar's ``superres`` object).

    ``path`` is the ONNX file (beside the sidecar; it may not exist: :func:`verify_superres_file` checks it
    and its ``sha256`` when it is loaded), ``weights_path`` the same network's folded weights for the GPU
    renderer (:mod:`lp3d.lift.superres_weights`; :func:`verify_superres_weights`). The network maps a raw
    feature render ``features (B, in_channels, input_resolution, input_resolution)`` (the renderer's
    ``features`` output, rgb = its first 3 channels, values in about [-1, 1]) to ``image (B, 3,
    output_resolution, output_resolution)`` in about [-1, 1]. ``about`` is informational (how it was made, its
    scores).
    """

    path: Path
    input_resolution: int
    output_resolution: int
    in_channels: int
    sha256: str
    weights_path: Path
    weights_sha256: str
    about: dict[str, Any] | None = None

    @property
    def scale(self) -> int:
        return self.output_resolution // self.input_resolution


def check_decoder_array(where: str, arr: np.ndarray) -> None:
    """The decoder array ``where`` (``decoder.w0`` ...) has its :data:`DECODER_SHAPES` shape and is finite."""
    name = where.rsplit(".", 1)[-1]
    if arr.shape != DECODER_SHAPES[name]:
        raise ModelPackageError(f"{where}: shape must be {DECODER_SHAPES[name]}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ModelPackageError(f"{where}: contains NaN/Inf")


def check_sizes(where: str, image_size: int, triplane_resolution: int) -> None:
    """The encoder's input side and triplane side within :data:`MAX_IMAGE_SIZE` and
    :data:`MAX_TRIPLANE_RESOLUTION`, before anything is allocated from them."""
    if not 8 <= image_size <= MAX_IMAGE_SIZE:
        raise ModelPackageError(
            f"{where}: image_size must be in [8, {MAX_IMAGE_SIZE}], got {short_repr(image_size)}"
        )
    t, cap = triplane_resolution, MAX_TRIPLANE_RESOLUTION
    if not 2 <= t <= cap:
        raise ModelPackageError(f"{where}: triplane_resolution must be in [2, {cap}], got {short_repr(t)}")


def decoder_bound(decoder: tuple[np.ndarray, ...], planes_max: float) -> float:
    """A float64 bound on every value the decoder ``(w0, b0, w1, b1)`` computes from planes whose
    values are at most ``planes_max`` in size: the twin of the renderer's ``check_decoder_range``
    (``crates/renderer/src/renderer/upload.rs``), which refuses a triplane when this reaches float32's
    maximum."""
    w0, b0, w1, b1 = (np.abs(np.asarray(a, np.float64)) for a in decoder)
    p = float(planes_max)
    hidden = w0.sum(axis=1) * p + b0
    out = w1 @ (hidden + 1.0) + b1
    out[0] *= 2.0  # the ray marcher adds two raw densities before halving them
    return float(max(3.0 * p, out.max(), hidden.max()))


def check_decoder_range(where: str, decoder: tuple[np.ndarray, ...], planes_max: float = 1.0) -> None:
    """Refuse a decoder that overflows float32 on planes up to ``planes_max`` (at load: 1, the scale of
    real planes, which sit ~30 orders of magnitude below the limit), as the renderer would, later."""
    bound = decoder_bound(decoder, planes_max)
    if not bound * 1.001 < F32_MAX:
        raise ModelPackageError(
            f"{where}: the decoder overflows float32: on planes up to {planes_max:.3g} its values reach "
            f"{bound:.3e}, beyond float32's maximum {F32_MAX:.3e}"
        )


def check_scene_bounds(where: str, box_warp: float, ray_start: float, ray_end: float) -> None:
    """The scene bounds with :class:`~lp3d.render.settings.SceneBounds`' one check, errors naming
    ``where`` (the sidecar or the argument) and the field."""
    bad = SceneBounds(box_warp, ray_start, ray_end).problem()
    if bad is not None:
        field, what = bad
        raise ModelPackageError(f"{where}: {field} {what}")


_SHA256 = re.compile(r"[0-9a-f]{64}")


def parse_superres(where: str, entry: Any, folder: Path) -> SuperresEntry:
    """Validate a ``superres`` object; errors name the sidecar (``where``) and the field."""
    if not isinstance(entry, dict):
        raise ModelPackageError(f"{where}: field 'superres' must be an object, got {type(entry).__name__}")

    def field(name: str, kind: type) -> Any:
        if name not in entry:
            raise ModelPackageError(f"{where}: missing field 'superres.{name}'")
        value = entry[name]
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ModelPackageError(
                f"{where}: field 'superres.{name}' has the wrong type ({type(value).__name__})"
            )
        return value

    def file_field(name: str, suffix: str) -> str:
        """A file name beside the sidecar, ending in ``suffix``."""
        value = field(name, str)
        if Path(value).name != value or not value.lower().endswith(suffix):
            raise ModelPackageError(
                f"{where}: field 'superres.{name}' must be an {suffix} file name beside the sidecar, "
                f"got {short_repr(value)}"
            )
        return value

    def digest_field(name: str) -> str:
        value = field(name, str)
        if not _SHA256.fullmatch(value):
            raise ModelPackageError(f"{where}: field 'superres.{name}' must be 64 lowercase hex digits")
        return value

    model = file_field("model", ".onnx")
    r_in = field("input_resolution", int)
    r_out = field("output_resolution", int)
    channels = field("in_channels", int)
    if not 8 <= r_in <= 4096:
        raise ModelPackageError(
            f"{where}: field 'superres.input_resolution' must be in [8, 4096], got {short_repr(r_in)}"
        )
    ratio = r_out // r_in if r_out > 0 else 0
    if r_out % r_in or ratio < 2 or ratio & (ratio - 1) or r_out > 8192:
        raise ModelPackageError(
            f"{where}: field 'superres.output_resolution' ({short_repr(r_out)}) must be input_resolution "
            f"({r_in}) times a power of two >= 2 (and at most 8192)"
        )
    if channels != N_CHANNELS:
        raise ModelPackageError(
            f"{where}: field 'superres.in_channels' must be {N_CHANNELS} (the renderer's feature image), "
            f"got {short_repr(channels)}"
        )
    digest = digest_field("sha256")
    weights = file_field("weights", ".npz")
    weights_digest = digest_field("weights_sha256")
    about = entry.get("about")
    if about is not None and not isinstance(about, dict):
        raise ModelPackageError(f"{where}: field 'superres.about' must be an object")
    return SuperresEntry(
        path=folder / model,
        input_resolution=r_in,
        output_resolution=r_out,
        in_channels=channels,
        sha256=digest,
        weights_path=folder / weights,
        weights_sha256=weights_digest,
        about=about,
    )


def verify_superres_file(entry: SuperresEntry) -> None:
    """The SR's ONNX file exists and has the recorded SHA-256 (:class:`ModelPackageError` if not)."""
    _verify_file(entry.path, entry.sha256, "superres.model", "superres.sha256")


def verify_superres_weights(entry: SuperresEntry) -> None:
    """The SR's weights file exists and has the recorded SHA-256 (:class:`ModelPackageError` if not)."""
    _verify_file(entry.weights_path, entry.weights_sha256, "superres.weights", "superres.weights_sha256")


def _verify_file(path: Path, sha256: str, name_field: str, digest_field: str) -> None:
    if not path.is_file():
        raise ModelPackageError(
            f"{path}: no such file (the package's field '{name_field}' names it beside the sidecar)"
        )
    digest = file_sha256(path)
    if digest != sha256:
        raise ModelPackageError(
            f"{path}: its SHA-256 ({digest[:12]}…) differs from the package's field '{digest_field}' "
            f"({sha256[:12]}…): the file was changed or replaced after export"
        )


# ------------------------------------------------------------------------------------------ reading


def read_sidecar(side: Path) -> dict[str, Any]:
    """The sidecar's JSON object, checked to be of this format and version."""
    if not side.is_file():
        raise ModelPackageError(
            f"{side}: model package sidecar not found (a .onnx model needs its {side.name} beside it, "
            "written by lp3d.lift.model_package.save_model_package; see docs/model-package.md)"
        )
    data = parse_json(side, _read_capped(side, MAX_SIDECAR_BYTES), "model package sidecar")
    if not isinstance(data, dict) or data.get("format") != PACKAGE_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ModelPackageError(
            f"{side}: not an lp3d model package (format {short_repr(got)}, expected {PACKAGE_FORMAT!r})"
        )
    if data.get("format_version") != PACKAGE_FORMAT_VERSION:
        raise ModelPackageError(
            f"{side}: format_version {short_repr(data.get('format_version'))} is not supported "
            f"(this reader supports {PACKAGE_FORMAT_VERSION})"
        )
    return data


def _read_capped(path: Path, cap: int) -> str:
    """A text file of at most ``cap`` bytes (its size checked before it is read)."""
    from lp3d.render.npz_reader import read_regular_file

    try:  # a regular file only (a FIFO would wait for a writer), its size checked before it is read
        return read_regular_file(path, "a model package sidecar", cap).decode("utf-8")
    except ValueError as e:
        if isinstance(e, UnicodeDecodeError):
            raise ModelPackageError(f"{path}: unreadable model package sidecar ({e})") from None
        raise ModelPackageError(str(e)) from None
    except OSError as e:
        raise ModelPackageError(f"{path}: unreadable model package sidecar ({e})") from None


def parse_json(where: Path | str, text: str, what: str) -> Any:
    """``json.loads`` with every way it fails as a :class:`ModelPackageError` naming ``where``: bad
    syntax, nesting deeper than Python's recursion limit, an integer of more than 4300 digits."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ModelPackageError(f"{where}: unreadable {what} (nested too deeply)") from None
    except ValueError as e:  # JSONDecodeError, and int() of a huge number
        raise ModelPackageError(f"{where}: unreadable {what} ({e})") from None


def sidecar_field(side: Path, data: dict[str, Any], name: str, kind: type | tuple[type, ...]) -> Any:
    """The sidecar's field ``name``, of type ``kind`` (a bool is never a number here)."""
    if name not in data:
        raise ModelPackageError(f"{side}: missing field {name!r}")
    value = data[name]
    if isinstance(value, bool) or not isinstance(value, kind):
        raise ModelPackageError(f"{side}: field {name!r} has the wrong type ({type(value).__name__})")
    return value


def sidecar_number(side: Path, data: dict[str, Any], name: str) -> float:
    """The sidecar's number ``name`` as a float (an integer too large for one is refused here; the
    ranges are :func:`check_scene_bounds`')."""
    value = sidecar_field(side, data, name, (int, float))
    try:
        return float(value)
    except OverflowError:
        raise ModelPackageError(f"{side}: field {name!r} is too large ({short_repr(value)})") from None


def as_float32(where: str, value: Any) -> np.ndarray:
    """``value`` as a float32 array; a finite number beyond float32's range is refused, naming ``where``
    (a cast would make it Inf). Raises what ``np.asarray`` raises for values that are not numbers."""
    wide = np.asarray(value, dtype=np.float64)
    big = np.abs(wide[np.isfinite(wide)])
    if big.size and big.max() > F32_MAX:
        raise ModelPackageError(f"{where} has values beyond float32 (up to {big.max():.3e})")
    return wide.astype(np.float32)


def sidecar_decoder(side: Path, dec: dict[str, Any]) -> dict[str, np.ndarray]:
    """The sidecar's ``decoder`` object as float32 arrays of the decoder's shapes, finite."""
    arrays: dict[str, np.ndarray] = {}
    for name in DECODER_SHAPES:
        if name not in dec:
            raise ModelPackageError(f"{side}: decoder.{name} missing")
        try:
            arr = as_float32(f"{side}: decoder.{name}", dec[name])
        except (TypeError, ValueError, OverflowError) as e:
            if isinstance(e, ModelPackageError):
                raise
            raise ModelPackageError(
                f"{side}: decoder.{name} is not a numeric array ({short_text(e)})"
            ) from None
        try:
            check_decoder_array(f"decoder.{name}", arr)
        except ModelPackageError as e:
            raise ModelPackageError(f"{side}: {e}") from None
        arrays[name] = arr
    return arrays
