"""The ``.npz`` triplane file (spec: ``docs/triplane-format.md``), read and written safely.

Reads never unpickle (``allow_pickle=False``) and reject anything unexpected with a message naming
the file and the key; writes are atomic (temp file in the same directory, then ``os.replace``), so a
reader never sees a half-written file and a failed write leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from lp3d.triplane import TriplaneData, TriplaneError, occupancy_checksum

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
#: baked for (:func:`lp3d.triplane.occupancy_checksum`). Checked on load, not kept in TriplaneData.
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
        arrays["occupancy"] = _little_endian(tri.occupancy.astype(np.float32))
        arrays[CHECKSUM_KEY] = np.array(occupancy_checksum(tri), dtype="<i8")
    if tri.source is not None:
        arrays["source"] = np.array(tri.source, dtype="<U")  # 0-d unicode (UTF-32LE in the file)
    return arrays


def save_triplane(path: str | os.PathLike[str], tri: TriplaneData) -> None:
    """Write ``tri`` to ``path`` (exactly that name; no ``.npz`` is appended), atomically.

    The data goes to a temporary file in the same directory, is flushed to disk, then renamed over
    ``path``. On any failure the temporary file is removed and an existing ``path`` is untouched.
    """
    path = Path(path)
    tri.validate()
    arrays = _arrays_of(tri)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            # A file object, so numpy appends no ".npz"; our arrays are never object arrays (no pickle).
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    # Persist the rename itself (best effort; not every platform can fsync a directory).
    with contextlib.suppress(OSError):
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


class TriplaneFileError(ValueError):
    """A bad triplane file; the message names the file and, where there is one, the key."""


def _fail(path: Path, key: str | None, message: str) -> TriplaneFileError:
    where = f"{path}" if key is None else f"{path}: key '{key}'"
    return TriplaneFileError(f"{where}: {message}")


def _scalar(path: Path, key: str, arr: np.ndarray, kinds: str) -> np.ndarray:
    if arr.shape != () or arr.dtype.kind not in kinds:
        raise _fail(
            path, key, f"must be a 0-d scalar of kind {kinds!r}, got dtype {arr.dtype} shape {arr.shape}"
        )
    return arr


#: Accepted dtypes per array key (TriplaneData checks shapes and values; planes: float16/float32).
_ARRAY_DTYPES: dict[str, tuple[type, ...]] = {
    "planes": (np.float16, np.float32),
    "decoder_w0": (np.float32, np.float64),
    "decoder_b0": (np.float32, np.float64),
    "decoder_w1": (np.float32, np.float64),
    "decoder_b1": (np.float32, np.float64),
    "camera": (np.float32, np.float64),
    "occupancy": (np.float32,),
}


def _read_value(path: Path, key: str, arr: np.ndarray) -> object:
    """The TriplaneData value of one key, after the checks only the file level can do."""
    if arr.dtype.hasobject:  # unreachable with allow_pickle=False; kept as a guard
        raise _fail(path, key, "object arrays are not allowed")
    if key in ("box_warp", "ray_start", "ray_end"):
        return float(_scalar(path, key, arr, "fiu"))
    if key == "source":
        return str(_scalar(path, key, arr, "U")[()])
    allowed = _ARRAY_DTYPES[key]
    if arr.dtype not in allowed:
        names = " or ".join(np.dtype(t).name for t in allowed)
        raise _fail(path, key, f"dtype must be {names}, got {arr.dtype}")
    return arr


def load_triplane(path: str | os.PathLike[str]) -> TriplaneData:
    """Read a triplane ``.npz`` written by :func:`save_triplane` (or the Rust writer).

    Raises OSError if the file cannot be opened (missing, permission) and ValueError
    (:class:`TriplaneFileError`), naming the file and the key, for anything wrong with its content:
    not a zip / truncated / corrupt, pickled (object) arrays, missing or unknown keys, an unsupported
    ``format_version``, bad shapes, dtypes or values (NaN/Inf included).
    """
    path = Path(path)
    current: str | None = None  # the key being read, for error messages
    values: dict[str, object] = {}
    try:
        # Check the magic ourselves: for a non-zip, non-.npy file numpy's message talks about pickles.
        with open(path, "rb") as f:
            magic = f.read(6)
        if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")):
            raise _fail(path, None, "not an .npz (zip) file" + (" (empty)" if not magic else ""))
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise _fail(path, None, "is a single .npy array, not an .npz triplane file")
        with loaded as npz:
            keys = set(npz.files)
            # Check the version first, so a newer file is reported as such rather than by its new keys.
            if "format_version" not in keys:
                raise _fail(path, "format_version", "missing key (not an lp3d triplane file?)")
            current = "format_version"
            version = int(_scalar(path, current, npz[current], "iu"))
            if version != FORMAT_VERSION:
                raise _fail(
                    path, current, f"unknown format_version {version} (this reader supports {FORMAT_VERSION})"
                )
            missing = sorted(set(REQUIRED_KEYS) - keys)
            if missing:
                raise _fail(path, missing[0], f"missing required key(s) {missing}")
            extra = sorted(keys - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS) - {CHECKSUM_KEY})
            if extra:
                raise _fail(path, extra[0], f"unknown key(s) {extra} (format_version {FORMAT_VERSION})")
            if ("occupancy" in keys) != (CHECKSUM_KEY in keys):
                missing_key = CHECKSUM_KEY if "occupancy" in keys else "occupancy"
                raise _fail(path, missing_key, f"missing ('occupancy' and '{CHECKSUM_KEY}' go together)")
            checksum = None
            if CHECKSUM_KEY in keys:
                current = CHECKSUM_KEY
                checksum = int(_scalar(path, current, npz[current], "iu"))
            for key in sorted(keys - {"format_version", CHECKSUM_KEY}):
                current = key
                values[_FIELD_OF_KEY[key]] = _read_value(path, key, npz[key])
    except (TriplaneFileError, FileNotFoundError, PermissionError, IsADirectoryError):
        raise
    except ValueError as e:  # numpy: pickled/object data, bad .npy header, size mismatch
        raise _fail(path, current, f"unreadable ({e})") from e
    except (zipfile.BadZipFile, EOFError, OSError, KeyError) as e:
        raise _fail(path, current, f"truncated or corrupt file ({type(e).__name__}: {e})") from e
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
    return tri
