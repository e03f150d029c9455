"""Atomic file writes: a finished file appears whole under its name, or not at all.

Every writer in lp3d goes through here (``lp3d.triplane_io.save_triplane``, the model package, the
CLI's ``Staged`` outputs, checkpoints, figures), so they share three promises:

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

__all__ = ["atomic_path", "create_temp", "discard", "publish", "publish_all"]

#: Process-wide sequence number for temporary names (``next`` on a count is atomic).
_sequence = itertools.count()
#: Attempts at a fresh temporary name before giving up (a clash means a stale file or a pid reused).
_ATTEMPTS = 100


def create_temp(path: str | os.PathLike[str]) -> Path:
    """Create a new, empty temporary file beside ``path`` and return its path.

    The name is ``.<name>.<pid>-<n>-<random>.tmp<suffix>`` (``path``'s suffix kept, for writers that
    read the format from it), unique to this process and call; the file is created exclusively with
    mode ``0666 & ~umask``. Raises ``OSError`` if the folder cannot be written."""
    path = Path(path)
    for _ in range(_ATTEMPTS):
        tag = f"{os.getpid()}-{next(_sequence)}-{os.urandom(3).hex()}"
        tmp = path.parent / f".{path.name}.{tag}.tmp{path.suffix}"
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
    deleted. ``parents``: create missing folders above ``path`` first (else a missing folder is an
    ``OSError``)."""
    path = Path(path)
    if parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = create_temp(path)
    try:
        yield tmp
    except BaseException:
        discard(tmp)
        raise
    publish(tmp, path)
