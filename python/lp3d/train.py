"""``python -m lp3d.train``: distil a teacher into the LP3D encoder (``lp3d train`` is the same command).

The code is the package :mod:`lp3d.training`, whose docstring describes the recipe; this module keeps
the command and re-exports the names other code imports from ``lp3d.train``.
"""

from __future__ import annotations

from lp3d.training import (
    CHECKPOINT_FORMAT,
    DESCRIPTION,
    TEACHERS,
    TRAIN_CONFIGS,
    Batch,
    CheckpointError,
    NonFiniteError,
    SceneBounds,
    Student,
    TrainConfig,
    Trainer,
    add_arguments,
    build_parser,
    build_teacher,
    dataset_key,
    load_checkpoint,
    main,
    principal_planes,
    render_teacher,
    render_views,
    resolve_teacher_args,
    run_cli,
    student_from_checkpoint,
    teacher_superres_state,
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
]

if __name__ == "__main__":
    raise SystemExit(main())
