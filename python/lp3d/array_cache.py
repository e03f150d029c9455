"""Content-checked on-disk caches of named arrays: built whole or not at all, reused only when verified.

The CPU recipe's teacher dataset (:mod:`lp3d.training.synthetic_data`) and the SR fit's pairs
(:mod:`lp3d.superres_fit.fit`) are both expensive to make and cheap to keep, so both are cached in a
folder named by a hash of their key. This module is the one mechanism they share:

* :func:`build` makes a private temporary folder beside the destination, hands the caller its arrays
  as writable ``.npy`` memmaps (from each array's shape and dtype) to fill, and when the block
  succeeds flushes them, records the key and each array's shape, dtype and SHA-256 in ``meta.json``
  and renames the folder into place (:func:`lp3d.atomic.publish`: synced, one atomic rename). If the
  block fails, the temporary folder is deleted: nothing is left behind.
* :func:`load` reads a folder back and checks everything ``meta.json`` promises (the key, each
  array's presence, digest, shape and dtype, finite floats); anything else raises
  :class:`StaleCacheError` (or the caller's subclass) naming the file and what differs, so callers
  report the folder and rebuild it rather than reuse it.

A folder written under another digest (an older lp3d's ``blake2b``) is stale, not an error: its
``meta.json`` records no SHA-256, so it is reported and rebuilt like any other.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from lp3d.atomic import publish

__all__ = [
    "DIGEST",
    "Shapes",
    "StaleCacheError",
    "build",
    "file_digest",
    "file_sha256",
    "key_digest",
    "load",
    "load_or_build",
    "reuse",
]

T = TypeVar("T")

#: The digest ``meta.json`` records for each array (the key under which it is recorded).
DIGEST = "sha256"
META = "meta.json"

#: ``{name: (shape, dtype)}``: the arrays of one cache, stored as ``<name>.npy``.
Shapes = Mapping[str, tuple[tuple[int, ...], str]]


class StaleCacheError(ValueError):
    """A cache folder that does not match its key or the digests in its ``meta.json``."""


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes, as 64 lowercase hex digits."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


#: The one digest of an array file (SHA-256 hex); the model package hashes its files alike.
file_digest = file_sha256


def key_digest(key: Mapping[str, Any]) -> str:
    """A short hash of ``key`` (JSON-serialisable) that names its cache folder: 20 hex digits."""
    text = json.dumps(dict(key), sort_keys=True)
    return hashlib.blake2b(text.encode(), digest_size=10).hexdigest()


def _canonical(key: Mapping[str, Any]) -> dict[str, Any]:
    """``key`` as ``meta.json`` holds it after a JSON round trip (tuples become lists)."""
    return json.loads(json.dumps(dict(key), sort_keys=True))


def _check_shapes(shapes: Shapes) -> dict[str, tuple[tuple[int, ...], np.dtype[Any]]]:
    out = {}
    for name, spec in shapes.items():
        # The name becomes a file name beside meta.json: keep it a plain word.
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"shapes: array name {name!r} must be a Python identifier")
        shape, dtype = spec
        if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
            raise ValueError(f"shapes[{name!r}]: shape {shape!r} must be non-negative ints")
        try:
            out[name] = (tuple(shape), np.dtype(dtype))
        except TypeError as e:
            raise ValueError(f"shapes[{name!r}]: dtype {dtype!r} is not a NumPy dtype ({e})") from None
    return out


@contextlib.contextmanager
def build(
    path: str | os.PathLike[str], key: Mapping[str, Any], shapes: Shapes
) -> Iterator[dict[str, np.memmap]]:
    """Yield ``{name: writable memmap}`` for ``shapes`` in a new temporary folder beside ``path``.

    When the block succeeds the arrays are flushed, digested and described in ``meta.json`` with
    ``key`` (JSON-serialisable), and the folder is renamed onto ``path``, which must not hold a
    non-empty folder (remove a stale one first). When the block fails the temporary folder is
    deleted and ``path`` is untouched. The yielded dict is emptied once the arrays are written."""
    path = Path(path)
    specs = _check_shapes(shapes)
    meta_key = _canonical(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        out = {
            name: np.lib.format.open_memmap(tmp / f"{name}.npy", mode="w+", dtype=dtype, shape=shape)
            for name, (shape, dtype) in specs.items()
        }
        yield out
        for a in out.values():
            a.flush()
        out.clear()  # drop our maps before hashing the files they wrote
        arrays = {
            name: {"shape": list(shape), "dtype": dtype.name, DIGEST: file_digest(tmp / f"{name}.npy")}
            for name, (shape, dtype) in specs.items()
        }
        meta = {"key": meta_key, "arrays": arrays}
        (tmp / META).write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        publish(tmp, path)  # a folder: fsynced, renamed in one step, its parent fsynced
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _key_difference(found: dict[str, Any], want: dict[str, Any]) -> str:
    """The first few fields where two keys differ, e.g. ``views: 3 -> 2`` (recorded -> wanted)."""
    names = sorted(set(found) | set(want))
    diff = [
        f"{n}: {found.get(n, '(none)')} -> {want.get(n, '(none)')}"
        for n in names
        if found.get(n) != want.get(n)
    ]
    shown = [d if len(d) <= 80 else d[:77] + "..." for d in diff[:3]]
    return "; ".join(shown) + ("; ..." if len(diff) > 3 else "")


def load(
    path: str | os.PathLike[str],
    key: Mapping[str, Any],
    shapes: Shapes,
    *,
    error: type[StaleCacheError] = StaleCacheError,
    mmap: bool = False,
) -> dict[str, np.ndarray]:
    """The arrays of the cache folder ``path``, verified against ``key`` and ``shapes``.

    Raises ``error`` (a :class:`StaleCacheError`) naming the file and what does not match: an
    unreadable ``meta.json`` or one made for another key, a missing array, a digest that differs
    (corrupt or edited), a shape or dtype that differs, NaN or Inf in a float array. ``mmap``:
    return read-only memmaps instead of arrays read into memory."""
    path = Path(path)
    specs = _check_shapes(shapes)
    meta_path = path / META
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as e:
        raise error(f"{meta_path}: unreadable ({e})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("key"), dict):
        raise error(f"{meta_path}: has no key (not a cache folder's meta.json)")
    want_key = _canonical(key)
    if meta["key"] != want_key:
        raise error(f"{meta_path}: made for another key ({_key_difference(meta['key'], want_key)})")
    recorded = meta.get("arrays")
    recorded = recorded if isinstance(recorded, dict) else {}
    arrays: dict[str, np.ndarray] = {}
    for name, (shape, dtype) in specs.items():
        file = path / f"{name}.npy"
        entry = recorded.get(name)
        entry = entry if isinstance(entry, dict) else {}
        if not file.is_file():
            raise error(f"{file}: missing")
        if DIGEST not in entry:
            raise error(f"{file}: {META} records no SHA-256 for it (an older or foreign cache)")
        if entry.get("shape") != list(shape) or entry.get("dtype") != dtype.name:
            raise error(
                f"{file}: {META} records shape {entry.get('shape')} {entry.get('dtype')}, "
                f"expected {list(shape)} {dtype.name}"
            )
        if file_digest(file) != entry[DIGEST]:
            raise error(f"{file}: its SHA-256 differs from {META} (corrupt or edited)")
        try:
            a = np.load(file, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise error(f"{file}: unreadable ({e})") from None
        if a.shape != shape or a.dtype != dtype:
            raise error(f"{file}: shape {a.shape} {a.dtype}, expected {shape} {dtype}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise error(f"{file}: holds NaN or Inf")
        arrays[name] = a
    return arrays


def reuse(path: str | os.PathLike[str], load: Callable[[], T], warning: str) -> T | None:
    """``load()`` if the folder ``path`` exists and verifies. A folder that raises
    :class:`StaleCacheError` is reported on stderr (``warning: <warning>: <reason>``) and deleted, so
    the caller rebuilds it; None then, and when there is no folder."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        return load()
    except StaleCacheError as e:
        print(f"warning: {warning}: {e}", file=sys.stderr)
        shutil.rmtree(path, ignore_errors=True)
        return None


def load_or_build(
    path: str | os.PathLike[str], load: Callable[[], T], build: Callable[[], object], warning: str
) -> T:
    """``load()`` of a verified folder at ``path``; else (none there, or stale: reported and deleted,
    see :func:`reuse`) ``build()`` it, then ``load()`` it (so what is returned was verified too)."""
    cached = reuse(path, load, warning)
    if cached is not None:
        return cached
    build()
    return load()
