"""A small, strict reader for NumPy ``.npy`` arrays inside ``.npz`` (zip) files: little-endian numeric
dtypes and unicode scalars only, never pickle. The Python twin of ``crates/renderer/src/npz.rs``:
the same header grammar, dtypes and limits, so both readers accept and refuse the same files.

:func:`open_regular_file` and :func:`read_npz` are the one way lp3d opens an ``.npz`` or another file
someone else made (triplanes, baked fields, checkpoint parts): a regular file, opened without
blocking, its size bounded before a byte is read.

Nothing the file claims is trusted before it is checked: the zip's declared entry sizes are held
against the file's real size and :data:`MAX_ENTRY_BYTES` before an entry is opened, and a ``.npy``
header's shape and dtype against the entry's size before its data is read. A hostile size claim is
an error (:class:`NpzError`), never an allocation.
"""

from __future__ import annotations

import os
import stat
import zipfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO

import numpy as np

#: Largest accepted ``.npy`` entry (the largest legal array, 2048 x 2048 float32 planes, is 1.5 GiB).
MAX_ENTRY_BYTES = 2 << 30
#: Most entries an ``.npz`` may list (a triplane file has at most 13 keys).
MAX_ENTRIES = 32
#: Largest ``.npy`` header text (numpy's own default cap; numpy writes about 128 bytes).
MAX_NPY_HEADER_BYTES = 10_000

_NPY_MAGIC = b"\x93NUMPY"
#: Accepted ``descr`` strings (besides ``<U{n}``) and their numpy dtypes.
_NUMERIC = {"<f2": "<f2", "<f4": "<f4", "<f8": "<f8", "<i4": "<i4", "<i8": "<i8"}
#: Bytes read per call while filling an array (bounds zipfile's temporary copies).
_CHUNK = 16 << 20


class NpzError(ValueError):
    """A bad ``.npz``; ``key`` names the entry ('' for the archive as a whole)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key
        self.message = message


@dataclass(frozen=True)
class NpyHeader:
    """What a ``.npy`` header declares, checked against the size of the bytes after it."""

    descr: str  # one of _NUMERIC or "<U{n}"
    shape: tuple[int, ...]
    data_offset: int  # bytes before the data: magic, version, header length, header text
    data_bytes: int  # bytes the shape and dtype imply (equal to what follows the header)

    @property
    def unicode_chars(self) -> int | None:
        """``n`` of a ``<U{n}`` dtype, else None."""
        return int(self.descr[2:]) if self.descr.startswith("<U") else None


def shape_text(shape: tuple[int, ...]) -> str:
    """A shape as Python writes a tuple: ``()``, ``(25,)``, ``(3, 32, 8, 8)``."""
    return repr(tuple(shape))


def parse_dtype(descr: str) -> str:
    """``descr`` if accepted: little-endian ``f2 f4 f8 i4 i8`` or ``<U{n}``; else NpzError."""
    if descr in _NUMERIC:
        return descr
    if "O" in descr:
        raise ValueError("object arrays are not allowed (they would need pickle)")
    n = descr[2:]
    if descr.startswith("<U") and 1 <= len(n) <= 10 and all("0" <= c <= "9" for c in n):
        return descr
    raise ValueError(f"unsupported dtype '{descr}'")


class _HeaderParser:
    """The header dict's grammar, the subset of Python literals numpy writes:
    ``{'descr': '<f4', 'fortran_order': False, 'shape': (3, 32, 8, 8), }`` plus padding. Strings
    without escapes, ``True``/``False``, tuples of decimal integers (one element needs its comma).
    ``npz.rs`` parses the same grammar, so both readers agree on every header."""

    def __init__(self, text: str) -> None:
        self.s = text
        self.i = 0

    def peek(self) -> str:
        return self.s[self.i] if self.i < len(self.s) else ""

    def ws(self) -> None:
        while self.peek() in (" ", "\t", "\n", "\r") and self.peek():
            self.i += 1

    def eat(self, c: str) -> bool:
        self.ws()
        if self.peek() == c:
            self.i += 1
            return True
        return False

    def expect(self, c: str) -> None:
        if not self.eat(c):
            raise ValueError(f"bad .npy header: expected '{c}' at offset {self.i}")

    def string(self) -> str:
        self.ws()
        q = self.peek()
        if q not in ("'", '"') or not q:
            raise ValueError(f"bad .npy header: expected a string at offset {self.i}")
        end = self.s.find(q, self.i + 1)
        if end < 0:
            raise ValueError("bad .npy header: unterminated string")
        text = self.s[self.i + 1 : end]
        if "\\" in text:
            raise ValueError("bad .npy header: escapes in strings are not supported")
        self.i = end + 1
        return text

    def int(self) -> int:
        self.ws()
        start = self.i
        while "0" <= self.peek() <= "9" and self.peek():
            self.i += 1
        digits = self.s[start : self.i]
        if not digits:
            raise ValueError(f"bad .npy header: expected a non-negative integer at offset {start}")
        value = int(digits)
        if value >= 2**64:  # usize in the Rust reader
            raise ValueError(f"bad .npy header: dimension {digits} is too large")
        return value

    def value(self) -> str | bool | tuple[int, ...]:
        self.ws()
        for word, flag in (("True", True), ("False", False)):
            if self.s.startswith(word, self.i):
                self.i += len(word)
                return flag
        if self.eat("("):
            dims: list[int] = []
            if self.eat(")"):
                return ()
            while True:
                dims.append(self.int())
                if self.eat(")"):
                    if len(dims) == 1:
                        raise ValueError("bad .npy header: a 1-d shape needs its trailing comma, as in (5,)")
                    return tuple(dims)
                self.expect(",")
                if self.eat(")"):
                    return tuple(dims)
        return self.string()


def parse_header_dict(text: str) -> tuple[str, bool, tuple[int, ...]]:
    """(descr, fortran_order, shape) of a header dict: exactly those three keys, once each."""
    p = _HeaderParser(text)
    found: dict[str, object] = {}
    p.expect("{")
    while not p.eat("}"):
        key = p.string()
        p.expect(":")
        value = p.value()
        if key == "descr" and not isinstance(value, str):
            raise ValueError("bad .npy header: 'descr' must be a string")
        if key == "fortran_order" and not isinstance(value, bool):
            raise ValueError("bad .npy header: 'fortran_order' must be True or False")
        if key == "shape" and not isinstance(value, tuple):
            raise ValueError("bad .npy header: 'shape' must be a tuple of integers")
        if key not in ("descr", "fortran_order", "shape"):
            raise ValueError(f"bad .npy header: unexpected key '{key}'")
        if key in found:
            raise ValueError(f"bad .npy header: key '{key}' appears twice")
        found[key] = value
        if not p.eat(","):
            p.expect("}")
            break
    p.ws()
    if p.i != len(text):
        raise ValueError(f"bad .npy header: unexpected text after the dict at offset {p.i}")
    for key in ("descr", "fortran_order", "shape"):
        if key not in found:
            raise ValueError(f"bad .npy header: no '{key}'")
    return found["descr"], found["fortran_order"], found["shape"]  # type: ignore[return-value]


def _read_exact(f: IO[bytes], n: int) -> bytes:
    data = f.read(n)
    if len(data) != n:
        raise ValueError("truncated data")
    return data


def read_npy_header(f: IO[bytes], entry_bytes: int) -> NpyHeader:
    """Read and check a ``.npy`` header from ``f``, an entry of ``entry_bytes`` bytes in all. Leaves
    ``f`` at the data, which is then exactly ``data_bytes`` long. Raises ValueError."""
    if entry_bytes < 10:
        raise ValueError(f"not a .npy array (only {entry_bytes} bytes)")
    pre = _read_exact(f, 8)
    if pre[:6] != _NPY_MAGIC:
        raise ValueError("not a .npy array (bad magic)")
    major, minor = pre[6], pre[7]
    if (major, minor) == (1, 0):
        length, prefix = int.from_bytes(_read_exact(f, 2), "little"), 10
    elif (major, minor) in ((2, 0), (3, 0)):
        length, prefix = int.from_bytes(_read_exact(f, 4), "little"), 12
    else:
        raise ValueError(f"unsupported .npy version {major}.{minor}")
    if length > MAX_NPY_HEADER_BYTES:
        raise ValueError(f"header of {length} bytes is larger than the cap of {MAX_NPY_HEADER_BYTES}")
    if prefix + length > entry_bytes:
        raise ValueError(f"truncated header: {length} bytes declared, the entry holds {entry_bytes} in all")
    raw = _read_exact(f, length)
    if not raw.isascii():
        raise ValueError("header is not ASCII text")
    descr, fortran, shape = parse_header_dict(raw.decode("ascii"))
    descr = parse_dtype(descr)
    if fortran:
        raise ValueError("Fortran-ordered arrays are not supported (write C order)")
    if descr.startswith("<U") and shape != ():
        raise ValueError(f"a unicode array must be 0-d (one string), got shape {shape_text(shape)}")
    # Overflow checked as the Rust reader's usize arithmetic does, in the same order.
    count = 1
    for dim in shape:
        count *= dim
        if count >= 2**64:
            raise ValueError(f"shape {shape_text(shape)} of {descr} is too large")
    item = 4 * int(descr[2:]) if descr.startswith("<U") else int(descr[2:])
    data_bytes = count * item
    if data_bytes >= 2**64:
        raise ValueError(f"shape {shape_text(shape)} of {descr} is too large")
    data_offset = prefix + length
    have = entry_bytes - data_offset
    if data_bytes > have:
        raise ValueError(
            f"truncated data: shape {shape_text(shape)} of {descr} needs {data_bytes} bytes, "
            f"the entry holds {have}"
        )
    if data_bytes < have:
        raise ValueError(
            f"{have - data_bytes} unexpected bytes after the data (shape {shape_text(shape)} of {descr} "
            f"needs {data_bytes})"
        )
    return NpyHeader(descr, shape, data_offset, data_bytes)


def read_npy_data(f: IO[bytes], header: NpyHeader) -> np.ndarray | str:
    """The data ``header`` describes (an array, or a str for ``<U{n}``), read straight into its
    buffer; then checks ``f`` is at its end (for a zip entry, that is what verifies its CRC-32)."""
    chars = header.unicode_chars
    if chars is not None:
        raw = _read_exact(f, header.data_bytes)
        try:
            text = raw.decode("utf-32-le")
        except UnicodeDecodeError as e:
            raise ValueError(f"invalid unicode ({e.reason})") from None
        value: np.ndarray | str = text.rstrip("\0")  # numpy pads with NULs; an inner NUL is kept
    else:
        arr = np.empty(header.shape, dtype=np.dtype(header.descr))
        view = memoryview(arr.reshape(-1).view(np.uint8))
        at = 0
        while at < header.data_bytes:
            got = f.readinto(view[at : at + _CHUNK])  # type: ignore[attr-defined]
            if not got:
                raise ValueError("truncated data")
            at += got
        value = arr
    if f.read(1):
        raise ValueError("data continues past its declared size")
    return value


class NpzReader:
    """An ``.npz`` whose container has been checked: at most :data:`MAX_ENTRIES` entries, no name
    twice, every entry stored (not compressed), unencrypted, and declaring a size within
    :data:`MAX_ENTRY_BYTES` and within the file. Entries are read by key, header first."""

    def __init__(self, file: IO[bytes], file_bytes: int) -> None:
        try:
            self._zip = zipfile.ZipFile(file)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, OverflowError) as e:
            raise NpzError("", f"not a valid .npz (zip) file: {e}") from None
        infos = self._zip.infolist()
        if any(n > 1 for n in Counter(i.filename for i in infos).values()):
            raise NpzError("", "the archive lists an entry name twice")
        if len(infos) > MAX_ENTRIES:
            raise NpzError("", f"{len(infos)} entries, more than the cap of {MAX_ENTRIES}")
        self._entries: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            key = info.filename.removesuffix(".npy")
            if info.flag_bits & 0x1:
                raise NpzError(key, "encrypted entries are not supported")
            if info.compress_type != zipfile.ZIP_STORED:
                raise NpzError(
                    key,
                    f"entry is compressed (method {info.compress_type}); triplane files are uncompressed "
                    "(numpy.savez, not savez_compressed)",
                )
            size, stored = info.file_size, info.compress_size
            if size != stored:
                raise NpzError(
                    key, f"stored entry declares {stored} bytes in the file but {size} bytes of data"
                )
            if size > MAX_ENTRY_BYTES:
                raise NpzError(key, f"entry declares {size} bytes, more than the cap of {MAX_ENTRY_BYTES}")
            # Its local header (30 bytes at least) and data lie inside the file.
            if info.header_offset + 30 + size > file_bytes:
                raise NpzError(
                    key,
                    f"entry declares {size} bytes at offset {info.header_offset}, past the end of the "
                    f"{file_bytes}-byte file",
                )
            self._entries[key] = info

    def keys(self) -> list[str]:
        """Keys (entry names less ``.npy``), in archive order."""
        return list(self._entries)

    def _open(self, key: str) -> IO[bytes]:
        try:
            return self._zip.open(self._entries[key])
        except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError, RuntimeError) as e:
            raise NpzError(key, f"corrupt entry: {e}") from None

    def header(self, key: str) -> NpyHeader:
        """The entry's ``.npy`` header, checked against the entry's size; no data is read."""
        with self._open(key) as f:
            try:
                return read_npy_header(f, self._entries[key].file_size)
            except NpzError:
                raise
            except (ValueError, zipfile.BadZipFile, OSError, EOFError) as e:
                raise NpzError(key, _message(e)) from None

    def read(self, key: str, header: NpyHeader) -> np.ndarray | str:
        """The entry's data as ``header`` (from :meth:`header`) describes it; CRC-checked."""
        with self._open(key) as f:
            try:
                _read_exact(f, header.data_offset)
                return read_npy_data(f, header)
            except (ValueError, zipfile.BadZipFile, OSError, EOFError) as e:
                raise NpzError(key, _message(e)) from None

    def close(self) -> None:
        self._zip.close()


def _message(e: BaseException) -> str:
    if isinstance(e, ValueError) and not isinstance(e, zipfile.BadZipFile):
        return str(e)
    if isinstance(e, EOFError):
        return "truncated data"
    return f"corrupt data ({e})"


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "is a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "is a character device"
    if stat.S_ISBLK(mode):
        return "is a block device"
    if stat.S_ISSOCK(mode):
        return "is a socket"
    return "is not a regular file"


def open_regular_file(path: str | os.PathLike[str], what: str) -> tuple[IO[bytes], int]:
    """``path`` opened for reading, and its size, after checking it is a regular file; ``what`` says
    what it should have been ("a triplane .npz"). Opened non-blocking: a FIFO would otherwise wait for
    a writer forever (for a regular file the flag changes nothing). A directory is an
    ``IsADirectoryError``, a FIFO, device or socket an ``OSError``, both naming the path."""
    flags = os.O_RDONLY
    for name in ("O_NONBLOCK", "O_NOCTTY", "O_CLOEXEC", "O_BINARY"):
        flags |= getattr(os, name, 0)
    fd = os.open(path, flags)  # FileNotFoundError / PermissionError, naming the path
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError(f"{os.fspath(path)}: is a directory, not a regular file ({what})")
        if not stat.S_ISREG(st.st_mode):
            raise OSError(f"{os.fspath(path)}: {_kind(st.st_mode)}, not a regular file ({what})")
        return os.fdopen(fd, "rb"), st.st_size
    except BaseException:
        os.close(fd)
        raise


def read_regular_file(path: str | os.PathLike[str], what: str, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path`` (see :func:`open_regular_file`), refused with a
    ``ValueError`` naming it when it is larger than ``max_bytes``, before it is read."""
    file, size = open_regular_file(path, what)
    with file:
        if size > max_bytes:
            raise ValueError(f"{os.fspath(path)}: {size} bytes, more than {what}'s cap of {max_bytes}")
        data = file.read(max_bytes + 1)
    if len(data) != size:
        raise ValueError(f"{os.fspath(path)}: changed while it was read ({what})")
    return data


def read_npz(
    file: IO[bytes],
    file_bytes: int,
    check_header: Callable[[str, NpyHeader], None] | None = None,
) -> dict[str, np.ndarray | str]:
    """Every entry of the ``.npz`` open in ``file`` (``file_bytes`` long, from
    :func:`open_regular_file`), by key. ``check_header(key, header)`` sees each entry's header and
    raises :class:`NpzError` for one the caller's format refuses, before any data is read; so every
    allocation is one the caller agreed to. Raises :class:`NpzError` naming the key."""
    if file.read(6) == _NPY_MAGIC:
        raise NpzError("", "is a single .npy array, not an .npz archive")
    file.seek(0)
    npz = NpzReader(file, file_bytes)
    try:
        headers = {key: npz.header(key) for key in npz.keys()}
        if check_header is not None:
            for key, header in headers.items():
                check_header(key, header)
        return {key: npz.read(key, header) for key, header in headers.items()}
    finally:
        npz.close()


def read_torch_file(path: str | os.PathLike[str], what: str, map_location: object = "cpu") -> object:
    """What ``torch.save`` wrote to ``path``, its tensors on ``map_location``, read with
    ``weights_only=True`` (tensors, numbers,
    strings and containers: no code is unpickled) after the checks of :func:`open_regular_file`
    (a FIFO is an ``OSError``, not a hang). A file that is not in torch's zip format, is damaged, or
    holds what ``weights_only`` refuses, is a ``ValueError`` of one line naming the file and ``what``
    it should have been ("a training checkpoint")."""
    import torch  # the one caller family that needs it; everything else here is numpy

    file, _ = open_regular_file(path, what)
    with file:
        # A zip's first local header; a torch file cut short (a full disk) still starts with it and is
        # reported by torch.load below as damaged, not as some other kind of file.
        if file.read(4) != b"PK\x03\x04":
            raise ValueError(f"{os.fspath(path)}: not a PyTorch file (torch.save's zip format; {what})")
        file.seek(0)
        try:
            return torch.load(file, map_location=map_location, weights_only=True)
        except Exception as e:  # torch raises many types (UnpicklingError, RuntimeError, KeyError ...)
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ValueError(f"{os.fspath(path)}: cannot be read as {what}: {first[:300]}") from None
