"""The one cosine learning-rate schedule of lp3d (:func:`cosine_decay`): the CPU training recipe's
decay (:func:`lp3d.training.optim.student_lr_factor`) and the super-resolution fit's
(:mod:`lp3d.superres_fit.train`).

Imports nothing (plain math), so that any layer that trains a network may use it."""

from __future__ import annotations

import math

__all__ = ["cosine_decay"]


def cosine_decay(step: int, total: int, final: float = 0.0) -> float:
    """The multiplier at ``step`` of a half cosine from 1 at step 0 to ``final`` at ``total`` steps
    (held at ``final`` after them): ``final + (1 - final) * (1 + cos(pi * t)) / 2``, ``t = step / total``."""
    t = min(1.0, step / total)
    return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * t))
