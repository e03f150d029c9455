"""One PSNR and one cosine schedule: every user calls the same function
(``tests/project/test_layout.py`` checks that no module defines another), and the numbers each user computed
before stay what they were: the evaluation's PSNR and both learning-rate schedules bit for bit, the
super-resolution fit's PSNR (once computed on a [0, 1] scale) and ``lp3d encode --refine``'s to float
rounding."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from lp3d.nets.lr_schedule import cosine_decay
from lp3d.render.psnr import psnr, psnr_db


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(4, 3, 8, 8, generator=g) * 0.8  # some pixels beyond [-1, 1]
    return a, a + 0.1 * torch.randn(4, 3, 8, 8, generator=g)


def test_every_psnr_is_the_one() -> None:
    from lp3d.evaluation import metrics
    from lp3d.lift import refine
    from lp3d.superres_fit import train

    assert metrics.psnr is psnr and train.psnr is psnr and refine.psnr_db is psnr_db


def test_the_psnr_is_the_evaluations_bit_for_bit() -> None:
    a, b = _pair()
    mse = (a.clamp(-1, 1) - b.clamp(-1, 1)).square().flatten(1).mean(dim=1)
    assert torch.equal(psnr(a, b), 10.0 * torch.log10(4.0 / mse.clamp_min(1e-12)))  # report.json's
    assert torch.equal(psnr(3 * a, b), psnr((3 * a).clamp(-1, 1), b))  # clipped to the range first
    assert psnr(a, a).tolist() == pytest.approx([10 * math.log10(4e12)] * 4)  # a perfect match: finite


def test_the_super_resolution_fits_psnr_is_unchanged_to_rounding() -> None:
    a, b = _pair(1)
    old = -10 * torch.log10(((a.clamp(-1, 1) - b.clamp(-1, 1)) / 2).square().flatten(1).mean(1))
    assert torch.allclose(psnr(a, b), old, rtol=0, atol=1e-4)


def test_psnr_db_is_one_pair_of_the_psnr() -> None:
    a, b = _pair(2)
    x, y = a[0].numpy(), b[0].numpy()
    x64, y64 = np.clip(x.astype(np.float64), -1, 1), np.clip(y.astype(np.float64), -1, 1)
    old = 10.0 * math.log10(4.0 / float(np.square(x64 - y64).mean()))  # refine's, in float64
    assert psnr_db(x, y) == pytest.approx(old, rel=1e-12)
    assert psnr_db(a[0], b[0]) == psnr_db(x, y)


def test_both_learning_rate_schedules_are_the_cosine_they_were() -> None:
    from lp3d.superres_fit.config import FitConfig
    from lp3d.superres_fit.train import _lr
    from lp3d.training import TRAIN_CONFIGS
    from lp3d.training.optim import student_lr_factor

    def cosine(final: float, t: float) -> float:  # the formula both computed before
        return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * t))

    cfg = TRAIN_CONFIGS["small"]
    assert cfg.lr_cosine_decay and cfg.lr_rampup_steps > 0
    for step in (0, 1, 7, cfg.lr_rampup_steps, cfg.total_steps // 3, cfg.total_steps, cfg.total_steps + 9):
        ramp = min(1.0, (step + 1) / cfg.lr_rampup_steps)
        want = ramp * cosine(cfg.lr_final_factor, min(1.0, step / cfg.total_steps))
        assert student_lr_factor(cfg, step) == want, step
    fit = dataclasses.replace(FitConfig(), steps=300)
    for step in (0, 1, 150, 299, 300, 301):
        want = fit.lr * cosine(fit.lr_final_factor, min(step / fit.steps, 1.0))
        assert _lr(fit, step) == want, step
    assert cosine_decay(0, 10) == 1.0 and cosine_decay(10, 10, 0.05) == 0.05 == cosine_decay(99, 10, 0.05)
