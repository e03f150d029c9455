"""What a resumed run must share with the checkpoint it continues: its configuration (every field but
those :data:`lp3d.training.config.RUN_KEEPING_FIELDS` lets change) and its teacher.

May import the modules of :mod:`lp3d.training` before it (``config``, ``checkpoint``)."""

from __future__ import annotations

from typing import Any

from lp3d.training.checkpoint import CheckpointError
from lp3d.training.config import TrainConfig, config_differences


def check_resumable(ckpt: dict[str, Any], cfg: TrainConfig, teacher_name: str) -> None:
    """Raise :class:`CheckpointError` when the loaded checkpoint ``ckpt`` (its ``train_config``,
    ``teacher`` and ``path``) was trained with another configuration than ``cfg`` or another teacher
    than ``teacher_name``."""
    diff = config_differences(ckpt["train_config"], cfg)
    if diff:
        shown = "\n  ".join(diff[:12]) + ("\n  ..." if len(diff) > 12 else "")
        raise CheckpointError(
            f"checkpoint {ckpt['path']!r} was trained with configuration "
            f"{ckpt['train_config'].name!r}, which differs from the requested {cfg.name!r}:\n"
            f"  {shown}\nresume with the checkpoint's own configuration (omit --config/--batch) "
            "or start a new run"
        )
    if ckpt["teacher"] != teacher_name:
        raise CheckpointError(
            f"checkpoint {ckpt['path']!r} was trained with teacher {ckpt['teacher']!r}, not {teacher_name!r}"
        )
