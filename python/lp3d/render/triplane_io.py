"""The ``.npz`` triplane file (spec: ``docs/triplane-format.md``), read and written safely.

Reads never unpickle (a strict reader of our own, :mod:`lp3d.render.npz_reader`, checks every size the file
claims before allocating) and reject anything unexpected with a message naming the file and the key;
writes are atomic (temp file in the same directory, then ``os.replace``), so a reader never sees a
half-written file and a failed write leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import io
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.atomic import atomic_path
from lp3d.render import npz_reader
from lp3d.render.camera import camera_summary, validate_camera
from lp3d.render.settings import HIDDEN, N_CHANNELS, N_OUT, SceneBounds
from lp3d.render.triplane import MAX_OCCUPANCY_RESOLUTION, TriplaneData, TriplaneError, occupancy_checksum

#: Version written by :func:`save_triplane`; the only one :func:`load_triplane` accepts.
FORMAT_VERSION = 1

#: Required keys and the TriplaneData field each fills.
REQUIRED_KEYS: dict[str, str] = {
    "planes": "planes",
    "decoder_w0": "w0",
    "decoder_b0": "b0",
    "decoder_w1": "w1",
    "decoder_b1": "b1",
    "box_warp": "box_warp",
    "ray_start": "ray_start",
    "ray_end": "ray_end",
    "format_version": "format_version",
}
#: Optional keys and their TriplaneData fields.
OPTIONAL_KEYS: dict[str, str] = {"camera": "camera", "occupancy": "occupancy", "source": "source"}

#: Stored with ``occupancy`` (and only with it): the CRC-32 of the planes and decoder the grid was
#: baked for (:func:`lp3d.render.triplane.occupancy_checksum`). Checked on load, and kept in
#: ``TriplaneData.occupancy_checksum``.
CHECKSUM_KEY = "occupancy_checksum"

_FIELD_OF_KEY = {**REQUIRED_KEYS, **OPTIONAL_KEYS}
_KEY_OF_FIELD = {f: k for k, f in _FIELD_OF_KEY.items()}


def _little_endian(arr: np.ndarray) -> np.ndarray:
    """C-contiguous little-endian copy-if-needed, so simple readers (the Rust side) need no other cases."""
    dt = arr.dtype
    if dt.byteorder not in ("<", "|") and dt.itemsize > 1:
        dt = dt.newbyteorder("<")
    return np.ascontiguousarray(arr, dtype=dt)


def _arrays_of(tri: TriplaneData) -> dict[str, np.ndarray]:
    arrays = {
        "planes": _little_endian(tri.planes),  # float16 stays float16
        "decoder_w0": _little_endian(tri.w0.astype(np.float32)),
        "decoder_b0": _little_endian(tri.b0.astype(np.float32)),
        "decoder_w1": _little_endian(tri.w1.astype(np.float32)),
        "decoder_b1": _little_endian(tri.b1.astype(np.float32)),
        "box_warp": np.array(tri.box_warp, dtype="<f8"),
        "ray_start": np.array(tri.ray_start, dtype="<f8"),
        "ray_end": np.array(tri.ray_end, dtype="<f8"),
        "format_version": np.array(FORMAT_VERSION, dtype="<i8"),
    }
    if tri.camera is not None:
        arrays["camera"] = np.array(tri.camera, dtype="<f8")
    if tri.occupancy is not None:
        if tri.occupancy_checksum is None:
            # A grid of unknown origin gets the checksum of these planes only once it is shown to
            # bound their density (the renderer's check against a fresh bake), so a grid baked for
            # other planes is never written as if it were theirs.
            _check_grid_bounds(tri)
        arrays["occupancy"] = _little_endian(tri.occupancy.astype(np.float32))
        arrays[CHECKSUM_KEY] = np.array(occupancy_checksum(tri), dtype="<i8")
    if tri.source is not None:
        arrays["source"] = np.array(tri.source, dtype="<U")  # 0-d unicode (UTF-32LE in the file)
    return arrays


def _check_grid_bounds(tri: TriplaneData) -> None:
    """TriplaneError naming ``occupancy`` unless ``tri``'s grid bounds its planes' density."""
    from lp3d.render.native import native_triplane

    try:
        native_triplane(tri)
    except ValueError as e:
        raise TriplaneError("occupancy", str(e).removeprefix("occupancy: ")) from None


def save_triplane(path: str | os.PathLike[str], tri: TriplaneData) -> None:
    """Write ``tri`` to ``path`` (exactly that name; no ``.npz`` is appended), atomically.

    The data goes to a new temporary file in the same directory, is flushed to disk, then renamed
    over ``path``; the file gets the usual permissions (``0666 & ~umask``). On any failure the
    temporary file is removed and an existing ``path`` is untouched. Safe to call from several threads
    or processes on one path: each publishes a complete file and the last rename wins.
    """
    path = Path(path)
    tri.validate()
    _check_writable_caps(path, tri)
    arrays = _arrays_of(tri)
    # A temporary file of this call's own (threads and processes may save one path at once), with
    # the permissions of any new file; synced, renamed, and deleted on failure (lp3d.atomic).
    with atomic_path(path, parents=False) as tmp, open(tmp, "wb") as f:
        # A file object, so numpy appends no ".npz"; our arrays are never object arrays (no pickle).
        np.savez(f, **arrays)


def triplane_bytes(tri: TriplaneData) -> bytes:
    """The ``.npz`` file :func:`save_triplane` writes for ``tri``, in memory (``lp3d serve``'s
    download, which writes nothing to the server's disk)."""
    tri.validate()
    _check_writable_caps(Path("<memory>"), tri)
    buffer = io.BytesIO()
    np.savez(buffer, **_arrays_of(tri))
    return buffer.getvalue()


def _check_writable_caps(path: Path, tri: TriplaneData) -> None:
    """Refuse to write a file the readers would refuse (the caps of :data:`FILE_LIMITS`)."""
    h, w = tri.planes.shape[-2:]
    if max(h, w) > MAX_PLANE_SIZE:
        raise _fail(path, "planes", f"{h}x{w} planes exceed the format's cap of {MAX_PLANE_SIZE} per side")
    if tri.source is not None and len(tri.source) > MAX_SOURCE_CHARS:
        raise _fail(path, "source", f"{len(tri.source)} characters, more than the cap of {MAX_SOURCE_CHARS}")


class TriplaneFileError(ValueError):
    """A bad triplane file; the message names the file and, where there is one, the key."""


def _fail(path: Path, key: str | None, message: str) -> TriplaneFileError:
    where = f"{path}" if key is None else f"{path}: key '{key}'"
    return TriplaneFileError(f"{where}: {message}")


#: Largest accepted triplane file (2048 x 2048 float32 planes and a 512^3 grid are just over 2 GiB).
MAX_FILE_BYTES = 3 << 30
#: Largest accepted plane side (H and W).
MAX_PLANE_SIZE = 2048
#: Longest accepted ``source`` text, in characters.
MAX_SOURCE_CHARS = 4096

#: The file format's caps (``docs/triplane-format.md``, "Caps"), by name. The Rust reader's
#: ``lp3d_render.FILE_LIMITS`` holds the same values (a test checks).
FILE_LIMITS: dict[str, int] = {
    "max_file_bytes": MAX_FILE_BYTES,
    "max_entry_bytes": npz_reader.MAX_ENTRY_BYTES,
    "max_entries": npz_reader.MAX_ENTRIES,
    "max_npy_header_bytes": npz_reader.MAX_NPY_HEADER_BYTES,
    "max_plane_size": MAX_PLANE_SIZE,
    "max_occupancy_resolution": MAX_OCCUPANCY_RESOLUTION,
    "max_source_chars": MAX_SOURCE_CHARS,
}

_REAL = ("<f2", "<f4", "<f8", "<i4", "<i8")
_FLOAT = ("<f4", "<f8")
#: Per key: accepted dtypes and the exact shape (None: checked below). The Rust reader's
#: ``check_header`` holds the same table.
_HEADER_SPEC: dict[str, tuple[tuple[str, ...], tuple[int, ...] | None]] = {
    "planes": (("<f2", "<f4"), None),
    "decoder_w0": (_FLOAT, (HIDDEN, N_CHANNELS)),
    "decoder_b0": (_FLOAT, (HIDDEN,)),
    "decoder_w1": (_FLOAT, (N_OUT, HIDDEN)),
    "decoder_b1": (_FLOAT, (N_OUT,)),
    "box_warp": (_REAL, ()),
    "ray_start": (_REAL, ()),
    "ray_end": (_REAL, ()),
    "format_version": (("<i4", "<i8"), ()),
    "occupancy_checksum": (("<i4", "<i8"), ()),
    "camera": (_FLOAT, (25,)),
    "occupancy": (("<f4",), None),
}
_DTYPE_NAMES = {"<f2": "float16", "<f4": "float32", "<f8": "float64", "<i4": "int32", "<i8": "int64"}


def _dtype_name(descr: str) -> str:
    return _DTYPE_NAMES.get(descr, f"{descr} (a string)")


def _check_header(key: str, h: npz_reader.NpyHeader) -> None:
    """One entry's ``.npy`` header (dtype, shape, caps) against the format, before its data is read."""
    if key == "source":
        n = h.unicode_chars
        if n is None:
            raise npz_reader.NpzError(
                key, f"dtype must be a unicode string (<U…), got {_dtype_name(h.descr)}"
            )
        if n > MAX_SOURCE_CHARS:
            raise npz_reader.NpzError(
                key, f"a string of {n} characters, more than the cap of {MAX_SOURCE_CHARS}"
            )
        return
    if key not in _HEADER_SPEC:
        return
    dtypes, want = _HEADER_SPEC[key]
    if h.descr not in dtypes:
        names = " or ".join(_dtype_name(d) for d in dtypes)
        raise npz_reader.NpzError(key, f"dtype must be {names}, got {_dtype_name(h.descr)}")
    shape, got = h.shape, npz_reader.shape_text(h.shape)
    if want is not None and shape != want:
        raise npz_reader.NpzError(key, f"shape must be {npz_reader.shape_text(want)}, got {got}")
    if key == "planes":
        if len(shape) != 4 or shape[0] != 3 or shape[1] != N_CHANNELS:
            raise npz_reader.NpzError(key, f"shape must be (3, {N_CHANNELS}, H, W), got {got}")
        height, width = shape[2], shape[3]
        if not (2 <= height <= MAX_PLANE_SIZE and 2 <= width <= MAX_PLANE_SIZE):
            raise npz_reader.NpzError(key, f"H and W must be in [2, {MAX_PLANE_SIZE}], got {height}x{width}")
    if key == "occupancy":
        if len(shape) != 3 or shape[1] != shape[0] or shape[2] != shape[0]:
            raise npz_reader.NpzError(key, f"shape must be (G, G, G), got {got}")
        if not 1 <= shape[0] <= MAX_OCCUPANCY_RESOLUTION:
            raise npz_reader.NpzError(
                key, f"G must be in [1, {MAX_OCCUPANCY_RESOLUTION}], got G = {shape[0]}"
            )


def _check_bounds(box_warp: float, ray_start: float, ray_end: float) -> None:
    """The scene bounds as stored, with :class:`~lp3d.render.settings.SceneBounds`' checks (as float64
    and as the renderer's float32, so ``ray_end = 1e300`` is an error here and in Rust alike)."""
    bad = SceneBounds(box_warp, ray_start, ray_end).problem()
    if bad is not None:
        raise npz_reader.NpzError(*bad)


def load_triplane(path: str | os.PathLike[str]) -> TriplaneData:
    """Read a triplane ``.npz`` written by :func:`save_triplane` (or the Rust writer).

    Raises OSError if the file cannot be opened (missing, permission) or is not a regular file (a
    directory, FIFO or device: at once, never a hang), and ValueError (:class:`TriplaneFileError`),
    naming the file and the key, for anything wrong with its content: not a zip, truncated or corrupt,
    compressed, too large for the caps (:data:`FILE_LIMITS`), pickled (object) arrays, missing or
    unknown keys, an unsupported ``format_version``, bad shapes, dtypes or values (NaN/Inf included).
    Every size the file claims is checked before anything is allocated. ``lp3d_render.Triplane.load``
    makes the same decisions (``tests/render/test_triplane_files.py``).
    """
    path = Path(path)
    file, size = npz_reader.open_regular_file(path, "a triplane .npz")
    with file:
        if size == 0:
            raise _fail(path, None, "empty file, not an .npz triplane")
        if size > MAX_FILE_BYTES:
            raise _fail(
                path, None, f"{size} bytes, more than the cap of {MAX_FILE_BYTES} for a triplane file"
            )
        try:
            if file.read(6) == b"\x93NUMPY":
                raise npz_reader.NpzError("", "is a single .npy array, not an .npz triplane file")
            file.seek(0)
            npz = npz_reader.NpzReader(file, size)
            try:
                values, checksum = _read_values(npz)
            finally:
                npz.close()
        except npz_reader.NpzError as e:
            raise _fail(path, e.key or None, e.message) from None
        except (OSError, zipfile.BadZipFile, EOFError) as e:  # a read failing mid-way
            raise _fail(path, None, f"truncated or corrupt file ({type(e).__name__}: {e})") from None
    try:
        tri = TriplaneData(**values)  # type: ignore[arg-type]
    except TriplaneError as e:
        raise _fail(path, _KEY_OF_FIELD.get(e.field, e.field), e.detail) from None
    if checksum is not None and checksum != (actual := occupancy_checksum(tri)):
        raise _fail(
            path,
            CHECKSUM_KEY,
            f"{checksum} does not match these planes and decoder ({actual}): the occupancy grid was "
            "baked for another triplane; bake it again",
        )
    # Kept with the grid, so that a grid carried over to other planes (dataclasses.replace) is refused.
    return tri if checksum is None else dataclasses.replace(tri, occupancy_checksum=checksum)


def _read_values(npz: npz_reader.NpzReader) -> tuple[dict[str, object], int | None]:
    """TriplaneData's arguments and the stored occupancy checksum, in the order of checks the Rust
    reader follows: the version, the set of keys, every header, then the data."""
    keys = sorted(npz.keys())
    version_key = "format_version"
    # The version first, so a newer file is reported as such rather than by its new keys.
    if version_key not in keys:
        raise npz_reader.NpzError(version_key, "missing key (not an lp3d triplane file?)")
    header = npz.header(version_key)
    _check_header(version_key, header)
    version = int(np.asarray(npz.read(version_key, header))[()])
    if version != FORMAT_VERSION:
        raise npz_reader.NpzError(
            version_key, f"unknown format_version {version} (this reader supports {FORMAT_VERSION})"
        )
    unknown = [k for k in keys if k not in REQUIRED_KEYS and k not in OPTIONAL_KEYS and k != CHECKSUM_KEY]
    if unknown:
        raise npz_reader.NpzError(unknown[0], f"unknown key(s) {unknown} (format_version {FORMAT_VERSION})")
    missing = sorted(set(REQUIRED_KEYS) - set(keys))
    if missing:
        raise npz_reader.NpzError(missing[0], f"missing required key(s) {missing}")
    if ("occupancy" in keys) != (CHECKSUM_KEY in keys):
        absent = CHECKSUM_KEY if "occupancy" in keys else "occupancy"
        raise npz_reader.NpzError(absent, f"missing ('occupancy' and '{CHECKSUM_KEY}' go together)")

    # Every header against the format before any data is read: no claim reaches the allocator.
    headers = {}
    for key in keys:
        if key != version_key:
            headers[key] = npz.header(key)
            _check_header(key, headers[key])
    data = {key: npz.read(key, h) for key, h in headers.items()}

    values: dict[str, object] = {}
    for key in ("planes", "decoder_w0", "decoder_b0", "decoder_w1", "decoder_b1", "occupancy", "source"):
        if key in data:
            values[_FIELD_OF_KEY[key]] = data[key]
    bounds = [float(np.asarray(data[k])[()]) for k in ("box_warp", "ray_start", "ray_end")]
    _check_bounds(*bounds)
    values["box_warp"], values["ray_start"], values["ray_end"] = bounds
    if "camera" in data:
        camera = np.asarray(data["camera"], dtype=np.float64)
        try:
            validate_camera(camera)
        except ValueError as e:
            raise npz_reader.NpzError("camera", str(e)) from None
        with np.errstate(over="ignore"):
            bad = np.flatnonzero(~np.isfinite(camera.astype(np.float32)))
        if bad.size:
            i = int(bad[0])
            raise npz_reader.NpzError("camera", f"value {camera[i]} at index {i} is not finite as float32")
        values["camera"] = camera
    checksum = int(np.asarray(data[CHECKSUM_KEY])[()]) if CHECKSUM_KEY in data else None
    return values, checksum


def triplane_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What a triplane file holds, as plain data (``lp3d info`` prints it): the file, planes and
    decoder statistics, bounds, camera (:func:`~lp3d.render.camera.camera_summary`), source, occupancy."""
    path = Path(path)
    tri = load_triplane(path)
    version = FORMAT_VERSION  # the only version load_triplane accepts
    planes = tri.planes.astype(np.float32)
    info: dict[str, Any] = {
        "file": str(path),
        "file_size": path.stat().st_size,
        "format_version": version,
        "planes": {
            "shape": list(tri.planes.shape),
            "dtype": str(tri.planes.dtype),
            "min": float(planes.min()),
            "max": float(planes.max()),
            "mean": float(planes.mean()),
            "std": float(planes.std()),
            "per_plane_std": [float(planes[p].std()) for p in range(3)],
        },
        "decoder": {
            name: {
                "shape": list(a.shape),
                "min": float(a.min()),
                "max": float(a.max()),
                "mean": float(a.mean()),
                "rms": float(np.sqrt(np.mean(np.square(a, dtype=np.float64)))),
            }
            for name, a in (("w0", tri.w0), ("b0", tri.b0), ("w1", tri.w1), ("b1", tri.b1))
        },
        "box_warp": tri.box_warp,
        "box": [-tri.box_warp / 2.0, tri.box_warp / 2.0],
        "ray_start": tri.ray_start,
        "ray_end": tri.ray_end,
        "camera": None if tri.camera is None else camera_summary(tri.camera),
        "source": tri.source,
        "occupancy": None,
    }
    # A hidden unit does nothing when its input row or its output column is all zeros.
    used = np.abs(tri.w0).sum(axis=1) * np.abs(tri.w1).sum(axis=0)
    info["decoder"]["hidden_units_used"] = int(np.count_nonzero(used))
    info["decoder"]["density_bias"] = float(tri.b1[0])
    if tri.occupancy is not None:
        occ = tri.occupancy
        info["occupancy"] = {
            "shape": list(occ.shape),
            "min": float(occ.min()),
            "max": float(occ.max()),
            "fraction_nonzero": float(np.count_nonzero(occ) / occ.size),
        }
    return info
