"""The one PSNR of lp3d: renders and photos in the renderer's colour range [-1, 1] (peak-to-peak 2),
each clipped to that range first, the mean squared error floored at 1e-12 (so a perfect match reads
about 126 dB, not infinity). Every score in dB uses it: ``lp3d eval``'s report.json
(:mod:`lp3d.evaluation.metrics`), the training run's learning curve (``heldout.csv``), the
super-resolution fit's report and ``lp3d encode --refine``'s input-view PSNR. A set of images scores
the mean of its per-image PSNRs.

Needs torch; imports nothing of lp3d."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["psnr", "psnr_db"]


def psnr(a: Tensor, b: Tensor) -> Tensor:
    """Per-image PSNR (dB) of images (B, C, H, W) in [-1, 1] (peak-to-peak 2) -> (B,)."""
    mse = (a.clamp(-1, 1) - b.clamp(-1, 1)).square().flatten(1).mean(dim=1)
    return 10.0 * torch.log10(4.0 / mse.clamp_min(1e-12))


def psnr_db(a: np.ndarray | Tensor, b: np.ndarray | Tensor) -> float:
    """:func:`psnr` of one image pair (any equal shapes, e.g. (3, H, W)) as a float, in float64."""
    x = torch.as_tensor(a, dtype=torch.float64)
    y = torch.as_tensor(b, dtype=torch.float64)
    return float(psnr(x.reshape(1, -1), y.reshape(1, -1))[0])
