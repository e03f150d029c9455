"""A training run's directory: who may write it, which checkpoint a run continues from, and what a
killed run leaves behind.

::

    runs/small/
      .lock                       held (``flock``) by the one trainer writing this run
      config.json  log.csv  heldout.csv
      checkpoints/step-NNNNNN.pt  the last ``keep_checkpoints``, each written atomically
      checkpoints/superseded-at-step-NNNNNN/
                                  checkpoints newer than the one a run was resumed from, set aside
      samples/step-NNNNNN.png

Promises (``docs/reliability.md``): one trainer per run directory at a time; a ``kill -9`` at any
moment leaves the newest complete checkpoint loadable and its temporary file is removed by the next
trainer; an unreadable newest checkpoint falls back, with a warning, to the newest readable one; a
run continued from an older checkpoint never mixes its steps with the newer ones.

Which checkpoint a reader takes (the step parsed from the name; the newest readable one) is
:mod:`lp3d.lift.run_checkpoints`, shared with ``lp3d encode --model RUN`` and re-exported here.
"""

from __future__ import annotations

import errno
import os
import sys
from pathlib import Path
from typing import Any

from lp3d.lift.run_checkpoints import checkpoint_path, checkpoints, latest_checkpoint, newest_readable

__all__ = [
    "RunBusyError",
    "RunLock",
    "checkpoint_path",
    "checkpoints",
    "latest_checkpoint",
    "newest_readable",
    "remove_stale_temporaries",
    "set_aside_checkpoints_after",
]


class RunBusyError(RuntimeError):
    """Another trainer holds the run directory's lock."""


def set_aside_checkpoints_after(run_dir: Path, step: int) -> list[Path]:
    """Move checkpoints newer than ``step`` into ``checkpoints/superseded-at-step-NNNNNN/``.

    A run continued from an older checkpoint writes its own later steps; leaving the old ones beside
    them would let the next ``--resume`` jump to a step of the abandoned branch. They are moved, not
    deleted, so nothing a user trained is lost. Returns the new paths."""
    later = [p for s, p in checkpoints(run_dir) if s > step]
    if not later:
        return []
    aside = Path(run_dir) / "checkpoints" / f"superseded-at-step-{step:06d}"
    aside.mkdir(exist_ok=True)
    moved = []
    for p in later:
        target = aside / p.name
        os.replace(p, target)
        moved.append(target)
    print(
        f"warning: continuing from step {step}; {len(moved)} newer checkpoint(s) "
        f"({', '.join(p.name for p in moved)}) moved to {aside}",
        file=sys.stderr,
    )
    return moved


def remove_stale_temporaries(run_dir: Path) -> list[Path]:
    """Delete the hidden temporary files (``.<name>.*.tmp*``) that an atomic write leaves when its
    process is killed mid-write. Call only while holding the run's :class:`RunLock`: a live trainer's
    temporary file is not stale."""
    removed = []
    for folder in (Path(run_dir), Path(run_dir) / "checkpoints", Path(run_dir) / "samples"):
        for p in folder.glob(".*.tmp*"):
            if p.is_file() and not p.is_symlink():
                p.unlink(missing_ok=True)
                removed.append(p)
    if removed:
        print(
            f"note: removed {len(removed)} temporary file(s) left by an interrupted write in {run_dir}",
            file=sys.stderr,
        )
    return removed


class RunLock:
    """An exclusive ``flock`` on ``run_dir/.lock``, so two trainers never write one run.

    The kernel drops the lock when its holder exits, ``kill -9`` included, so a crashed run never
    leaves the directory locked. Re-entrant for its holder (``acquire`` twice is a no-op)."""

    def __init__(self, run_dir: Path) -> None:
        self.path = Path(run_dir) / ".lock"
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> None:
        if self._fd is not None:
            return
        import fcntl  # POSIX only; lp3d trains on Linux and macOS

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = _read_holder(fd)
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RunBusyError(
                    f"run directory {str(self.path.parent)!r} is in use by another trainer{holder}; "
                    "wait for it to finish or choose another --out"
                ) from None
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def __del__(self) -> None:
        self.release()


def _read_holder(fd: int) -> str:
    try:
        pid = os.pread(fd, 32, 0).decode().strip()
    except OSError:
        return ""
    return f" (pid {pid})" if pid.isdigit() else ""
