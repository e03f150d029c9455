"""Which checkpoint of a training run folder is read: the one rule of ``lp3d encode --model RUN``
(:mod:`lp3d.lift.torch_backend`), ``lp3d eval RUN``, ``lp3d export RUN`` and ``--resume RUN``
(:func:`lp3d.training.checkpoint.load_checkpoint`).

A run folder keeps its checkpoints as ``checkpoints/step-NNNNNN.pt`` (:func:`checkpoint_path`); the
step is parsed from the name (so step 1,000,000 comes after step 999,999), other files are ignored,
and a reader takes the newest one it can read (:func:`newest_readable`): a newer file that a kill, a
full disk or a copy left damaged is skipped with a warning naming it.

Torch-free and imports nothing of lp3d, so that the lifting side and the training side (which may
import :mod:`lp3d.lift`) share it; :mod:`lp3d.training.run_dir` re-exports it with the rest of a run
folder's rules."""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

__all__ = ["checkpoint_path", "checkpoints", "latest_checkpoint", "newest_readable"]

_STEP_NAME = re.compile(r"step-(\d{6,})\.pt")
T = TypeVar("T")


def checkpoint_path(run_dir: Path, step: int) -> Path:
    """``run_dir/checkpoints/step-NNNNNN.pt``, where a run writes its checkpoint of ``step``."""
    return Path(run_dir) / "checkpoints" / f"step-{step:06d}.pt"


def checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    """``(step, path)`` of the run's checkpoints, oldest first (only ``step-NNNNNN.pt`` files)."""
    found = []
    for p in (Path(run_dir) / "checkpoints").glob("step-*.pt"):
        m = _STEP_NAME.fullmatch(p.name)
        if m and p.is_file():
            found.append((int(m.group(1)), p))
    return sorted(found)


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint with the highest step in ``run_dir/checkpoints``, or None (whether it can be
    read or not: :func:`newest_readable` reads one)."""
    found = checkpoints(run_dir)
    return found[-1][1] if found else None


def newest_readable(run_dir: Path, load: Callable[[Path], T], error: type[Exception]) -> T:
    """``load`` of the newest checkpoint that ``load`` accepts. A newer one that raises ``error``
    (truncated by a full disk, damaged by a copy) is skipped with a warning naming it and why;
    when none is readable, ``error`` lists them all."""
    found = checkpoints(run_dir)
    if not found:
        raise error(f"{str(run_dir)!r} holds no checkpoints (expected {run_dir}/checkpoints/step-*.pt)")
    problems = []
    for _, path in reversed(found):
        try:
            out = load(path)
        except error as e:
            problems.append(f"{path.name}: {e}")
            continue
        if problems:
            print(
                f"warning: skipped unreadable newer checkpoint(s), continuing from {path.name}:\n  "
                + "\n  ".join(problems),
                file=sys.stderr,
            )
        return out
    raise error(f"no checkpoint in {str(run_dir)!r} is readable:\n  " + "\n  ".join(problems))
