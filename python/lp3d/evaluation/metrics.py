"""The evaluation's measures: PSNR, depth errors and SSIM per view (:class:`ViewScores`), and the
cross-identity scores (:class:`CrossScores`: each identity's renders against its own teacher's and against the
other identities', whose difference is the identity specificity). Used by :mod:`lp3d.evaluation.evaluate`.
The PSNR is lp3d's one (:func:`lp3d.render.psnr.psnr`, re-exported here), the training's learning curve's
too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from lp3d.render.psnr import psnr
from lp3d.training.losses import LPIPSLoss, ssim

__all__ = ["CrossScores", "ViewScores", "depth_errors", "psnr"]


def depth_errors(pred: Tensor, target: Tensor, mask: Tensor) -> tuple[float, float]:
    """Scale-and-shift-invariant ``(L1, RMSE)`` of one depth map pair (H, W) over ``mask`` (H, W) bool.

    The target is normalised to [0, 1] over the mask (supplement "H3DS"), then ``a * pred + b`` is
    fitted to it by least squares and the residual measured. NaN when the mask has < 2 pixels.
    """
    m = mask.flatten()
    if int(m.sum()) < 2:
        return math.nan, math.nan
    p = pred.flatten()[m].double()
    g = target.flatten()[m].double()
    g = (g - g.min()) / (g.max() - g.min()).clamp_min(1e-12)
    design = torch.stack([p, torch.ones_like(p)], dim=1)
    coef = torch.linalg.lstsq(design, g.unsqueeze(1)).solution
    r = design @ coef - g.unsqueeze(1)
    return float(r.abs().mean()), float(r.square().mean().sqrt())


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else None


class ViewScores:
    """Accumulates per-view metrics of one method."""

    def __init__(self) -> None:
        self.values: dict[str, list[float]] = {}

    def add(
        self, prefix: str, pred: dict[str, Tensor], truth: dict[str, Tensor], lpips: LPIPSLoss | None
    ) -> None:
        def put(name: str, vals: Tensor | Sequence[float]) -> None:
            self.values.setdefault(f"{prefix}_{name}", []).extend(float(v) for v in vals)

        put("psnr", psnr(pred["high"], truth["high"]))
        put("psnr_raw", psnr(pred["raw"], truth["raw"]))
        put("ssim", ssim(pred["high"].clamp(-1, 1), truth["high"].clamp(-1, 1)))
        if lpips is not None:
            put("lpips", lpips.distance(pred["high"].clamp(-1, 1), truth["high"].clamp(-1, 1)))
        l1s, rmses = [], []
        for i in range(pred["depth"].shape[0]):
            a, b = depth_errors(pred["depth"][i], truth["depth"][i], truth["weights_sum"][i] > 0.5)
            l1s.append(a)
            rmses.append(b)
        put("depth_l1", l1s)
        put("depth_rmse", rmses)

    def summary(self) -> dict[str, float | None]:
        return {k: _mean(v) for k, v in sorted(self.values.items())}


@dataclass
class CrossScores:
    """Novel-view scores of one method's renders of identity i (rows) against the truth of identity j
    (columns), each the mean over the views: PSNR (high and raw) and SSIM, (n, n) arrays."""

    psnr: np.ndarray
    psnr_raw: np.ndarray
    ssim: np.ndarray

    @classmethod
    def of(
        cls, high: Sequence[Tensor], raw: Sequence[Tensor], truth: Sequence[dict[str, Tensor]]
    ) -> CrossScores:
        """``high``/``raw``: one method's renders per identity, or one render for all (the floor)."""
        n = len(truth)
        rows = len(high)
        out = {k: np.zeros((rows, n)) for k in ("psnr", "psnr_raw", "ssim")}
        for i in range(rows):
            h = high[i].clamp(-1, 1)
            for j in range(n):
                t = truth[j]
                out["psnr"][i, j] = float(psnr(h, t["high"]).mean())
                out["psnr_raw"][i, j] = float(psnr(raw[i], t["raw"]).mean())
                out["ssim"][i, j] = float(ssim(h, t["high"].clamp(-1, 1)).mean())
        if rows == 1:  # the same render for every identity
            out = {k: np.repeat(v, n, axis=0) for k, v in out.items()}
        return cls(**out)

    @staticmethod
    def _own_other(m: np.ndarray) -> tuple[list[float], list[float | None]]:
        n = m.shape[0]
        own = [float(m[i, i]) for i in range(n)]
        other = [float((m[i].sum() - m[i, i]) / (n - 1)) if n > 1 else None for i in range(n)]
        return own, other

    def per_identity(self) -> list[dict[str, float | None]]:
        """Per identity: own, other and specificity (own - other) for PSNR, raw PSNR and SSIM."""
        rows: list[dict[str, float | None]] = [{} for _ in range(self.psnr.shape[0])]
        for name, m, spec in (
            ("novel_psnr", self.psnr, "identity_specificity_db"),
            ("novel_psnr_raw", self.psnr_raw, "identity_specificity_raw_db"),
            ("novel_ssim", self.ssim, "identity_specificity_ssim"),
        ):
            own, other = self._own_other(m)
            for row, a, b in zip(rows, own, other, strict=True):
                row[name] = a
                row[f"{name}_other"] = b
                row[spec] = None if b is None else a - b
        return rows

    def summary(self) -> dict[str, float | None]:
        """Averages over identities of the "other" scores and of the specificities."""
        rows = self.per_identity()
        keys = (
            "novel_psnr_other",
            "novel_psnr_raw_other",
            "novel_ssim_other",
            "identity_specificity_db",
            "identity_specificity_raw_db",
            "identity_specificity_ssim",
        )
        return {k: _mean([r[k] for r in rows]) for k in keys}
