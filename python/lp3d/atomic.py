"""Atomic file writes: a finished file appears whole under its name, or not at all.

Every writer in lp3d goes through here, one file with :func:`atomic_path` (``save_triplane``, the
model package, checkpoints, figures; :func:`atomic_write_text` for a text file: ``config.json``,
``report.json``) or a set with :class:`StagedFiles` (the CLI's outputs), so they share three promises.
No other module defines an atomic writer of its own (``tests/project/test_layout.py`` checks):

* **Unique temporary names.** Each write gets its own new file beside the destination (same folder,
  so the rename is atomic), created with ``O_EXCL``: threads and processes writing the same path at
  once never share a temporary file, and each rename publishes one writer's complete file.
* **The usual permissions.** The temporary file is created with mode 0666, which the kernel reduces
  by the umask (and a folder's default ACL) exactly as for any new file, so an output is 0644 under
  the common umask 022, whichever writer made it. (``tempfile.mkstemp`` would make it 0600, and
  reading the umask with ``os.umask`` briefly sets it to 0 for every thread of the process.)
* **Durable and clean.** The data is fsynced before the rename and the folder after it (best
  effort); on any failure the temporary file is deleted and an existing destination is untouched.
"""

from __future__ import annotations

import contextlib
import itertools
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TypeVar

__all__ = [
    "StagedFiles",
    "atomic_path",
    "atomic_write_text",
    "create_temp",
    "discard",
    "publish",
    "publish_all",
]

#: Process-wide sequence number for temporary names (``next`` on a count is atomic).
_sequence = itertools.count()
#: Attempts at a fresh temporary name before giving up (a clash means a stale file or a pid reused).
_ATTEMPTS = 100


#: Bytes of the destination's name and suffix kept in a temporary name, so that it stays far below
#: the file system's limit (NAME_MAX, 255 bytes) for any legal destination name.
_NAME_BYTES = 64
_SUFFIX_BYTES = 16


def _prefix(text: str, limit: int) -> str:
    """The longest start of ``text`` whose file-system encoding fits ``limit`` bytes (whole characters)."""
    while len(os.fsencode(text)) > limit:
        text = text[: max(0, min(len(text) - 1, limit))]
    return text


def create_temp(path: str | os.PathLike[str]) -> Path:
    """Create a new, empty temporary file beside ``path`` and return its path.

    The name is ``.<name>.<pid>-<n>-<random>.tmp<suffix>`` (``path``'s suffix kept, for writers that
    read the format from it), unique to this process and call; the file is created exclusively with
    mode ``0666 & ~umask``. ``<name>`` is cut to its first 64 bytes and a suffix longer than 16 bytes
    is left out, so a destination name of any legal length (up to 255 bytes) has a temporary name
    within the limit too. Raises ``OSError`` if the folder cannot be written."""
    path = Path(path)
    name = _prefix(path.name, _NAME_BYTES)
    suffix = path.suffix if len(os.fsencode(path.suffix)) <= _SUFFIX_BYTES else ""
    for _ in range(_ATTEMPTS):
        tag = f"{os.getpid()}-{next(_sequence)}-{os.urandom(3).hex()}"
        tmp = path.parent / f".{name}.{tag}.tmp{suffix}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"{path}: no free temporary name beside it after {_ATTEMPTS} attempts")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)  # read-only: works whatever the file's mode
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    """Persist renames in ``folder`` (best effort: not every platform can fsync a folder)."""
    with contextlib.suppress(OSError):
        _fsync(folder)


def discard(tmp: Path) -> None:
    """Delete a temporary file if it is still there."""
    with contextlib.suppress(OSError):
        tmp.unlink()


def publish(tmp: Path, path: str | os.PathLike[str]) -> None:
    """Flush ``tmp`` to disk and rename it onto ``path``. On failure ``tmp`` is deleted."""
    publish_all([(tmp, Path(path))])


def publish_all(files: Sequence[tuple[Path, Path]]) -> None:
    """Publish ``(temporary, destination)`` pairs together: every file is flushed to disk first, then
    renamed in order. If a rename fails, the destinations already renamed in this call are removed
    again (they belong to an incomplete set) and every temporary file is deleted; the error is
    re-raised. A destination replaced before the failure keeps no old version."""
    done: list[Path] = []
    try:
        for tmp, _ in files:
            _fsync(tmp)
        for tmp, final in files:
            os.replace(tmp, final)
            done.append(final)
    except BaseException:
        for final in done:
            discard(final)
        for tmp, _ in files:
            discard(tmp)
        raise
    for folder in {final.parent for _, final in files}:
        _fsync_folder(folder)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, parents: bool = True) -> Iterator[Path]:
    """Yield a new temporary path beside ``path`` (see :func:`create_temp`) for the block to write.
    When the block succeeds the file is synced and renamed onto ``path``; when it fails it is
    deleted; an ``OSError`` that names no file (``write`` on a full disk) is made to name ``path``.
    ``parents``: create missing folders above ``path`` first (else a missing folder is an
    ``OSError``)."""
    path = Path(path)
    if parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = create_temp(path)
    try:
        yield tmp
    except BaseException as e:
        discard(tmp)
        if isinstance(e, OSError) and e.filename is None:  # a full disk found by write(): name the file
            e.filename = str(path)
        raise
    publish(tmp, path)


def atomic_write_text(path: str | os.PathLike[str], text: str, *, parents: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`atomic_path`; returns ``path``."""
    path = Path(path)
    with atomic_path(path, parents=parents) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


_Staged = TypeVar("_Staged", bound="StagedFiles")


class StagedFiles:
    """The multi-file :func:`atomic_path`: files written to temporaries beside their destinations and
    published together by :meth:`commit` (all or none, :func:`publish_all`).

    Leaving the ``with`` block without committing (an error, Ctrl-C) deletes every temporary file and
    every folder this object created, so a failed job leaves nothing behind::

        with StagedFiles() as staged:
            image.save(staged.temp(out / "a.png"))
            np.save(staged.temp(out / "b.npy"), array)
            staged.commit()
    """

    def __init__(self) -> None:
        self._files: list[tuple[Path, Path]] = []
        self._dirs: list[Path] = []

    def __enter__(self: _Staged) -> _Staged:
        return self

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        self.discard()

    def destination(self, path: str | os.PathLike[str] | None) -> Path | None:
        """The destination whose temporary file (or which itself) is ``path``, else None: to name
        the output in an error about one of ours (``path`` as in ``OSError.filename``)."""
        if path is None:
            return None
        return next((final for tmp, final in self._files if str(path) in (str(tmp), str(final))), None)

    @property
    def destinations(self) -> list[Path]:
        """The destinations staged so far, in order."""
        return [final for _, final in self._files]

    def mkdir(self, folder: Path) -> None:
        """Create ``folder`` (its parent must exist); it is removed again on failure if still empty."""
        if not folder.exists():
            folder.mkdir()
            self._dirs.append(folder)

    def temp(self, final: str | os.PathLike[str]) -> Path:
        """A new temporary file for ``final`` (:func:`create_temp`: same folder, so the rename is
        atomic; unique to this call; the usual permissions; ``final``'s suffix kept, which writers
        such as imageio/ffmpeg read the format from)."""
        final = Path(final)
        tmp = create_temp(final)
        self._files.append((tmp, final))
        return tmp

    def commit(self) -> list[Path]:
        """Sync every temporary file, then rename each onto its destination; returns the destinations.
        If a rename fails, the destinations already renamed are removed again (all or none) and the
        error is re-raised."""
        files = list(self._files)
        publish_all(files)
        self._files, self._dirs = [], []
        return [final for _, final in files]

    def discard(self) -> None:
        """Delete every temporary file not yet published and the folders created for them."""
        for tmp, _ in self._files:
            discard(tmp)
        for folder in reversed(self._dirs):
            with contextlib.suppress(OSError):
                folder.rmdir()
        self._files, self._dirs = [], []
