"""The optimisers of a training run: the student's Adam with one parameter group per part (encoder,
basis, transformer, decoder, super-resolution), the discriminator's Adam with EG3D's lazy-R1
adjustment, the student's learning-rate schedule (:func:`student_lr_factor`), and
:class:`Optimisation`, the part of a :class:`~lp3d.training.trainer.Trainer` that holds them with
their schedulers and the AMP gradient scaler.

May import the modules of :mod:`lp3d.training` before it (``config`` to ``student``) and
:mod:`lp3d.nets`; not ``trainer`` or ``cli``."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import torch

from lp3d.nets.discriminator import DualDiscriminator
from lp3d.nets.lr_schedule import cosine_decay
from lp3d.training.config import TrainConfig
from lp3d.training.student import Student


def build_optimisers(
    cfg: TrainConfig, student: Student, discriminator: DualDiscriminator
) -> tuple[torch.optim.Adam, torch.optim.Adam]:
    """``(opt_g, opt_d)``: the student's optimiser (its groups named, each with its learning rate) and
    the discriminator's."""
    enc = student.encoder
    basis_ids = {id(q) for q in enc.basis.parameters()} if enc.basis is not None else set()
    offset = [] if student.plane_offset is None else [student.plane_offset]
    betas = tuple(cfg.adam_betas)
    opt_g = torch.optim.Adam(
        [
            {
                "params": [*(q for q in enc.other_parameters() if id(q) not in basis_ids), *offset],
                "lr": cfg.lr_encoder,
                "name": "encoder",
            },
            {
                "params": [q for q in enc.other_parameters() if id(q) in basis_ids],
                "lr": cfg.lr_basis,
                "name": "basis",
            },
            {
                "params": list(enc.transformer_parameters()),
                "lr": cfg.lr_transformer,
                "name": "transformer",
            },
            {"params": list(student.decoder.parameters()), "lr": cfg.lr_decoder, "name": "decoder"},
            {
                "params": list(student.superres.parameters()),
                "lr": cfg.lr_superres,
                "name": "superres",
            },
        ],
        betas=betas,  # type: ignore[arg-type]
    )
    # EG3D's lazy regularisation: R1 every r1_interval steps, with lr and betas adjusted.
    ratio = cfg.r1_interval / (cfg.r1_interval + 1)
    opt_d = torch.optim.Adam(
        discriminator.parameters(),
        lr=cfg.lr_discriminator * ratio,
        betas=(cfg.discriminator_betas[0] ** ratio, cfg.discriminator_betas[1] ** ratio),
        eps=1e-8,
    )
    return opt_g, opt_d


def student_lr_factor(cfg: TrainConfig, step: int) -> float:
    """The student's learning-rate multiplier: a linear ramp over ``lr_rampup_steps``, then 1 (the
    paper), or with ``lr_cosine_decay`` a cosine to ``lr_final_factor`` at ``total_steps``
    (:func:`lp3d.nets.lr_schedule.cosine_decay`)."""
    ramp = min(1.0, (step + 1) / cfg.lr_rampup_steps) if cfg.lr_rampup_steps > 0 else 1.0
    if not cfg.lr_cosine_decay:
        return ramp
    return ramp * cosine_decay(step, cfg.total_steps, cfg.lr_final_factor)


@dataclass(eq=False)
class Optimisation:
    """The optimisers of a run (:func:`build_optimisers`), their learning-rate schedulers (the
    student's :func:`student_lr_factor`, the discriminator's constant) and the AMP gradient scaler
    (enabled only with ``amp``), at step 0."""

    opt_g: torch.optim.Adam
    opt_d: torch.optim.Adam
    sched_g: torch.optim.lr_scheduler.LambdaLR
    sched_d: torch.optim.lr_scheduler.LambdaLR
    scaler: torch.amp.GradScaler

    @classmethod
    def build(
        cls, cfg: TrainConfig, student: Student, discriminator: DualDiscriminator, *, amp: bool
    ) -> Optimisation:
        opt_g, opt_d = build_optimisers(cfg, student, discriminator)
        return cls(
            opt_g,
            opt_d,
            torch.optim.lr_scheduler.LambdaLR(opt_g, functools.partial(student_lr_factor, cfg)),
            torch.optim.lr_scheduler.LambdaLR(opt_d, lambda s: 1.0),
            torch.amp.GradScaler("cuda", enabled=amp),
        )

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint entries ``optimizer_g``, ``optimizer_d``, ``scheduler_g``, ``scheduler_d``
        and ``scaler``."""
        return {
            "optimizer_g": self.opt_g.state_dict(),
            "optimizer_d": self.opt_d.state_dict(),
            "scheduler_g": self.sched_g.state_dict(),
            "scheduler_d": self.sched_d.state_dict(),
            "scaler": self.scaler.state_dict(),
        }

    def load_optimisers(self, ckpt: dict[str, Any]) -> None:
        """The optimisers' states of a checkpoint (raises what ``load_state_dict`` raises when they do
        not fit)."""
        self.opt_g.load_state_dict(ckpt["optimizer_g"])
        self.opt_d.load_state_dict(ckpt["optimizer_d"])

    def load_schedules(self, ckpt: dict[str, Any]) -> None:
        """The schedulers' and the scaler's states of a checkpoint (a checkpoint without a scaler
        state keeps the fresh one)."""
        self.sched_g.load_state_dict(ckpt["scheduler_g"])
        self.sched_d.load_state_dict(ckpt["scheduler_d"])
        if ckpt.get("scaler"):
            self.scaler.load_state_dict(ckpt["scaler"])
