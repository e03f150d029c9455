"""``python -m lp3d.train``: distil a teacher into the LP3D encoder (``lp3d train`` is the same command).

The command line is :mod:`lp3d.cli.train`; the library it calls is :func:`lp3d.training.train` (the
package's docstring describes the recipe). This module keeps the README's command and re-exports the
names older code imports from ``lp3d.train``.
"""

from __future__ import annotations

from lp3d.cli.train import DESCRIPTION, add_arguments, build_parser, main
from lp3d.cli.train import run as run_cli
from lp3d.training import (
    CHECKPOINT_FORMAT,
    TEACHERS,
    TRAIN_CONFIGS,
    Batch,
    CheckpointError,
    NonFiniteError,
    SceneBounds,
    Student,
    TrainConfig,
    Trainer,
    TrainResult,
    build_teacher,
    dataset_key,
    load_checkpoint,
    principal_planes,
    render_teacher,
    render_views,
    resolve_teacher_args,
    student_from_checkpoint,
    teacher_superres_state,
    train,
)
from lp3d.training.config import _scaled_schedule as _scaled_schedule
from lp3d.training.run_dir import latest_checkpoint as latest_checkpoint

__all__ = [
    "CHECKPOINT_FORMAT",
    "DESCRIPTION",
    "TEACHERS",
    "TRAIN_CONFIGS",
    "Batch",
    "CheckpointError",
    "NonFiniteError",
    "SceneBounds",
    "Student",
    "TrainConfig",
    "TrainResult",
    "Trainer",
    "add_arguments",
    "build_parser",
    "build_teacher",
    "dataset_key",
    "load_checkpoint",
    "main",
    "principal_planes",
    "render_teacher",
    "render_views",
    "resolve_teacher_args",
    "run_cli",
    "student_from_checkpoint",
    "teacher_superres_state",
    "train",
]

if __name__ == "__main__":
    raise SystemExit(main())
