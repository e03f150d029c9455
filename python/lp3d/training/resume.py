"""What a resumed run must share with the checkpoint it continues: its configuration (every field but
those :data:`lp3d.training.config.RUN_KEEPING_FIELDS` lets change, a longer schedule and a ray phase
that starts among the steps not yet taken) and its teacher.

May import the modules of :mod:`lp3d.training` before it (``config``, ``checkpoint``)."""

from __future__ import annotations

import dataclasses
from typing import Any

from lp3d.training.checkpoint import CheckpointError
from lp3d.training.config import TrainConfig, config_differences


def extended_schedule(cfg: TrainConfig, total: int) -> TrainConfig:
    """``cfg``'s schedule lengthened to ``total`` steps, for a resumed run whose curve was still
    rising: the learning-rate cosine is stretched, stage boundaries stay where they were (a config
    that regresses for its whole schedule still does). Shortening is refused: steps already taken at
    a higher learning rate cannot be undone."""
    if total < cfg.total_steps:
        raise CheckpointError(
            f"--total-steps {total}: the checkpoint's schedule has {cfg.total_steps} steps; a resumed "
            "run may lengthen its schedule, not shorten it"
        )
    regression = total if cfg.regression_steps == cfg.total_steps else cfg.regression_steps
    return dataclasses.replace(cfg, total_steps=total, regression_steps=regression)


def with_ray_phase(cfg: TrainConfig, ray_from: int, step: int = 0) -> TrainConfig:
    """``cfg`` with the CPU recipe's ray phase (the RGB L1 on random rays beside L_tri) starting at
    step ``ray_from`` instead of ``cfg.regression_steps``. A run at ``step`` (a resumed one's checkpoint)
    may move the boundary only among the steps it has not taken: what it trained on stays as it was."""
    if cfg.recipe != "cpu":
        raise ValueError(
            f"--ray-from: configuration {cfg.name!r} uses the {cfg.recipe} recipe, which has no ray phase"
        )
    if cfg.rays_per_identity <= 0 or cfg.ray_weight <= 0:
        raise ValueError(
            f"--ray-from: configuration {cfg.name!r} renders no rays (rays_per_identity, ray_weight)"
        )
    if not step <= ray_from <= cfg.total_steps:
        raise ValueError(
            f"--ray-from {ray_from}: must be between the run's step {step} and its last step "
            f"{cfg.total_steps}"
        )
    return dataclasses.replace(cfg, regression_steps=ray_from)


def refuse_weights_only(ckpt: dict[str, Any]) -> dict[str, Any]:
    """``ckpt``, or :class:`CheckpointError` when it holds the student's weights alone
    (:func:`lp3d.training.checkpoint.weights_only_checkpoint`): nothing for ``--resume`` to continue."""
    if ckpt.get("weights_only"):
        raise CheckpointError(
            f"checkpoint {ckpt['path']!r} holds the student's weights alone, without the optimiser's "
            "state that --resume continues: evaluate or export it, or start a new run from it with "
            "--init-from"
        )
    return ckpt


def check_resumable(ckpt: dict[str, Any], cfg: TrainConfig, teacher_name: str) -> None:
    """Raise :class:`CheckpointError` when the loaded checkpoint ``ckpt`` (its ``train_config``,
    ``teacher`` and ``path``) was trained with another configuration than ``cfg`` or another teacher
    than ``teacher_name``, or holds the student's weights alone (``scripts/checkpoint_parts.py``)."""
    refuse_weights_only(ckpt)
    recorded: TrainConfig = ckpt["train_config"]
    if cfg.total_steps > recorded.total_steps:
        recorded = extended_schedule(recorded, cfg.total_steps)
    if cfg.regression_steps != recorded.regression_steps and cfg.regression_steps >= ckpt.get("step", 0):
        recorded = with_ray_phase(recorded, cfg.regression_steps, ckpt.get("step", 0))
    diff = config_differences(recorded, cfg)
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
