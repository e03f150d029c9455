"""The optimisers of a training run: the student's Adam with one parameter group per part (encoder,
basis, transformer, decoder, super-resolution), the discriminator's Adam with EG3D's lazy-R1
adjustment, and the student's learning-rate schedule (:func:`student_lr_factor`).

May import the modules of :mod:`lp3d.training` before it (``config`` to ``student``) and
:mod:`lp3d.nets`; not ``trainer`` or ``cli``."""

from __future__ import annotations

import math

import torch

from lp3d.nets.discriminator import DualDiscriminator
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
    paper), or with ``lr_cosine_decay`` a cosine to ``lr_final_factor`` at ``total_steps``."""
    ramp = min(1.0, (step + 1) / cfg.lr_rampup_steps) if cfg.lr_rampup_steps > 0 else 1.0
    if not cfg.lr_cosine_decay:
        return ramp
    t = min(1.0, step / cfg.total_steps)
    return ramp * (cfg.lr_final_factor + (1 - cfg.lr_final_factor) * 0.5 * (1 + math.cos(math.pi * t)))
