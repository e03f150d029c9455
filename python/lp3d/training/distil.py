"""Distil a teacher into the encoder, as one plain function: :func:`train`.

``python -m lp3d.train`` and ``lp3d train`` (:mod:`lp3d.cli.train`) parse their options into a call of
:func:`train`; code that trains from Python calls it directly::

    from lp3d.training import train
    result = train("tiny", out="runs/t", max_steps=20)
    print(result.step, result.checkpoint)

Errors are raised, not printed: :class:`ValueError` (an option, a configuration), :class:`OSError`
(a file), :class:`~lp3d.training.checkpoint.CheckpointError`,
:class:`~lp3d.training.steps.NonFiniteError` (a loss went NaN) and :class:`KeyboardInterrupt` (after a
line saying which checkpoint to continue from).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lp3d.training import distributed
from lp3d.training.checkpoint import CheckpointError, load_shared_checkpoint
from lp3d.training.config import TRAIN_CONFIGS, TrainConfig, scaled_schedule
from lp3d.training.losses import build_perceptual
from lp3d.training.resume import extended_schedule, refuse_weights_only, with_ray_phase
from lp3d.training.run_dir import latest_checkpoint
from lp3d.training.teacher_factory import build_teacher, recordable_teacher_args, resolve_teacher_args
from lp3d.training.trainer import Trainer

#: The configuration a fresh run gets when none is named.
DEFAULT_CONFIG = "tiny"


@dataclass(frozen=True)
class TrainResult:
    """What :func:`train` leaves: where the run stopped and its last checkpoint."""

    out: Path
    #: The global step the run reached.
    step: int
    #: The newest readable checkpoint in ``out`` (None on ranks other than 0 under torchrun).
    checkpoint: Path | None
    #: True when a SIGTERM stopped the run early (it saved a checkpoint first).
    interrupted: bool


def train(
    config: str | TrainConfig | None = None,
    *,
    out: str | Path | None = None,
    resume: str | Path | None = None,
    max_steps: int | None = None,
    teacher: str | None = None,
    teacher_pkl: str | None = None,
    eg3d_source: str | None = None,
    eg3d_conditioning: str | None = None,
    batch: int | None = None,
    total_steps: int | None = None,
    ray_from: int | None = None,
    perceptual: str | None = None,
    lpips_weights: str | None = None,
    data_cache: str | None = None,
    dataset_identities: int | None = None,
    lr_scale: float | None = None,
    checkpoint_every: int | None = None,
    device: str = "auto",
    dist_timeout_minutes: float = 60.0,
    progress: bool = True,
    init_from: str | Path | None = None,
) -> TrainResult:
    """Train the encoder of ``config`` (a name of :data:`TRAIN_CONFIGS`, a :class:`TrainConfig`, or
    None: ``tiny``, or the checkpoint's on ``resume``) into ``out`` (default ``runs/<config>``; on
    ``resume`` the checkpoint's run directory) up to ``max_steps`` (default: the schedule's end).

    ``resume`` is a checkpoint file or a run directory (its latest readable checkpoint). The other
    keywords override the configuration as ``python -m lp3d.train``'s options of the same names do
    (``--help`` says what each means). Under torchrun every process calls this; one process without
    torchrun trains alone."""
    try:
        _check_arguments(dist_timeout_minutes, resume, init_from)
        run_device = distributed.setup(device, timeout_minutes=dist_timeout_minutes).device
        # A weights-only checkpoint is refused here, before the teacher is built.
        ckpt = refuse_weights_only(load_shared_checkpoint(str(resume))) if resume is not None else None
        cfg, teacher_name, out_dir = _run_of(config, teacher, out, ckpt, resume)
        cfg = _with_overrides(
            cfg,
            ckpt,
            batch=batch,
            total_steps=total_steps,
            ray_from=ray_from,
            perceptual=perceptual,
            checkpoint_every=checkpoint_every,
            dataset_identities=dataset_identities,
            lr_scale=lr_scale,
        )
        loss = build_perceptual(cfg.perceptual, lpips_net=cfg.lpips_net, lpips_weights=lpips_weights)
        if loss is not None:
            loss = loss.to(run_device)
        targs = _teacher_args(ckpt, teacher_name, teacher_pkl, eg3d_source, eg3d_conditioning)
        run_teacher = build_teacher(
            teacher_name,
            triplane_resolution=cfg.triplane_resolution,
            teacher_pkl=targs["teacher_pkl"],
            eg3d_source=targs["eg3d_source"],
            conditioning=targs["conditioning"],  # type: ignore[arg-type]
            device=run_device,
        )
        trainer = Trainer(
            cfg,
            out_dir,
            teacher=run_teacher,
            teacher_name=teacher_name,
            perceptual=loss,
            device=run_device,
            resume=ckpt["path"] if ckpt is not None else None,
            progress=progress,
            data_cache=data_cache,
            teacher_args=targs,
            init_from=init_from,
        )
        distributed.note(
            f"training {cfg.name!r} on {run_device} with the {teacher_name} teacher, batch "
            f"{cfg.batch_size}, from step {trainer.step} to {max_steps or cfg.total_steps}; "
            f"run directory {out_dir}"
        )
        try:
            trainer.train(max_steps)
        except KeyboardInterrupt:
            distributed.note(f"aborted; the last checkpoint is {latest_checkpoint(out_dir)}")
            raise
        last = latest_checkpoint(out_dir) if trainer.is_main else None
        return TrainResult(out=out_dir, step=trainer.step, checkpoint=last, interrupted=trainer.interrupted)
    finally:
        distributed.shutdown()  # leaves torchrun's process group (a no-op for one process)


def _check_arguments(dist_timeout_minutes: float, resume: object, init_from: object) -> None:
    """The checks of :func:`train`'s arguments that need nothing built."""
    if not (math.isfinite(dist_timeout_minutes) and dist_timeout_minutes > 0):
        raise ValueError(
            f"dist_timeout_minutes must be a positive number of minutes, got {dist_timeout_minutes}"
        )
    if init_from is not None and resume is not None:
        raise ValueError("--init-from starts a new run; a resumed run continues its own weights")


def _run_of(
    config: str | TrainConfig | None,
    teacher: str | None,
    out: str | Path | None,
    ckpt: dict[str, Any] | None,
    resume: str | Path | None,
) -> tuple[TrainConfig, str, Path]:
    """``(config, teacher name, run directory)``: the checkpoint's on ``resume``, else the arguments'."""
    if ckpt is not None:
        cfg: TrainConfig = ckpt["train_config"]
        name = config.name if isinstance(config, TrainConfig) else config
        if name is not None and name != cfg.name:
            raise CheckpointError(
                f"--resume {resume}: the checkpoint was trained with configuration {cfg.name!r}, "
                f"not {name!r}; omit --config to resume it"
            )
        return cfg, teacher or ckpt["teacher"], Path(out) if out else Path(ckpt["path"]).parent.parent
    if isinstance(config, TrainConfig):
        cfg = config
    else:
        name = config or DEFAULT_CONFIG
        if name not in TRAIN_CONFIGS:
            raise ValueError(f"--config {name!r}: not one of {', '.join(sorted(TRAIN_CONFIGS))}")
        cfg = TRAIN_CONFIGS[name]
    return cfg, teacher or "procedural", Path(out) if out else Path("runs") / cfg.name


#: The student's learning rates, which ``--lr-scale`` multiplies (a warm start fine-tunes at a fraction).
STUDENT_RATES = ("lr_encoder", "lr_transformer", "lr_basis", "lr_decoder", "lr_superres")


def _with_overrides(
    cfg: TrainConfig,
    ckpt: dict[str, Any] | None,
    *,
    batch: int | None,
    total_steps: int | None,
    ray_from: int | None,
    perceptual: str | None,
    checkpoint_every: int | None,
    dataset_identities: int | None,
    lr_scale: float | None = None,
) -> TrainConfig:
    """``cfg`` with the arguments that override it; a resumed run may not change its dataset."""
    if batch is not None:
        if batch < 1:
            raise ValueError(f"--batch must be >= 1, got {batch}")
        cfg = dataclasses.replace(cfg, batch_size=batch)
    if total_steps is not None and total_steps < 1:
        raise ValueError(f"--total-steps must be >= 1, got {total_steps}")
    if total_steps is not None and ckpt is not None:
        # A resumed run's schedule is the checkpoint's, lengthened if asked; the same length again
        # (an interrupted extended run) is no change, not a fresh run's scaled schedule.
        if total_steps != cfg.total_steps:
            cfg = extended_schedule(cfg, total_steps)
            distributed.note(f"note: schedule extended to {total_steps} steps")
    elif total_steps is not None:
        cfg = dataclasses.replace(cfg, **scaled_schedule(total_steps, cfg))
    if ray_from is not None:
        cfg = with_ray_phase(cfg, ray_from, int(ckpt["step"]) if ckpt is not None else 0)
    if perceptual is not None:
        cfg = dataclasses.replace(cfg, perceptual=perceptual)
    if checkpoint_every is not None:
        if checkpoint_every < 1:
            raise ValueError(f"--checkpoint-every must be >= 1, got {checkpoint_every}")
        cfg = dataclasses.replace(cfg, checkpoint_every=checkpoint_every)
    if dataset_identities is not None:
        if ckpt is not None and dataset_identities != cfg.dataset_identities:
            raise CheckpointError(
                f"--dataset-identities {dataset_identities}: the checkpoint was trained on "
                f"{cfg.dataset_identities}; a resumed run keeps its dataset"
            )
        cfg = dataclasses.replace(cfg, dataset_identities=dataset_identities)
    if lr_scale is not None:
        if ckpt is not None:
            raise CheckpointError("--lr-scale sets a new run's rates; a resumed run keeps its checkpoint's")
        if not (math.isfinite(lr_scale) and 0.0 < lr_scale <= 10.0):
            raise ValueError(f"--lr-scale must be in (0, 10], got {lr_scale}")
        cfg = dataclasses.replace(cfg, **{k: getattr(cfg, k) * lr_scale for k in STUDENT_RATES})
    return cfg


def _teacher_args(
    ckpt: dict[str, Any] | None,
    teacher_name: str,
    teacher_pkl: str | None,
    eg3d_source: str | None,
    conditioning: str | None,
) -> dict[str, str | None]:
    """How to build the teacher: the arguments, else (for the same teacher) the run's recorded ones;
    a resumed run may not change the EG3D conditioning."""
    targs = resolve_teacher_args(
        ckpt if ckpt is not None and teacher_name == ckpt["teacher"] else None,
        teacher_pkl=teacher_pkl,
        eg3d_source=eg3d_source,
        conditioning=conditioning,
    )
    recorded = resolve_teacher_args(ckpt) if ckpt is not None else None
    if recorded is not None and recordable_teacher_args(targs) != recorded:  # recorded paths are absolute
        if targs["conditioning"] != recorded["conditioning"]:
            raise CheckpointError(
                f"--eg3d-conditioning {targs['conditioning']}: the run was trained with "
                f"{recorded['conditioning']!r}; a resumed run keeps its teacher"
            )
        distributed.note(f"note: teacher arguments differ from the run's recorded ones: {targs}")
    return targs
