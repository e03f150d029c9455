"""Training and scoring a super-resolution fit (steps 2 and 3 of :mod:`lp3d.superres_fit.fit`):
the starting network (:func:`new_superres`), its blocks on crops (:func:`synthesize`), the batches,
the learning-rate schedule (lp3d's cosine, :func:`lp3d.nets.lr_schedule.cosine_decay`), the training
loop (:func:`train_steps`) and the held-out score (:func:`score`, in lp3d's one PSNR,
:func:`lp3d.render.psnr.psnr`, re-exported here).

Imports lp3d.nets, lp3d.render.psnr, lp3d.training.losses and the other lp3d.superres_fit modules;
lp3d.images inside :func:`score`.
"""

from __future__ import annotations

import csv
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lp3d.nets.lr_schedule import cosine_decay
from lp3d.nets.superres import SuperResolution
from lp3d.render.psnr import psnr
from lp3d.superres_fit.config import FitConfig, FitError
from lp3d.superres_fit.data import PairSet
from lp3d.training.losses import SSIMGradientLoss, ssim

__all__ = ["new_superres", "psnr", "score", "synthesize", "train_steps"]


def new_superres(cfg: FitConfig) -> SuperResolution:
    """The network a fit starts from: EG3D's initialisation, seeded by ``cfg.seed``, with every ToRGB
    weight zeroed, so that its first output is the FIR-upsampled raw rgb (about what bilinear
    upsampling gives) and training learns the residual detail."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        sr = SuperResolution(cfg.superres_config())
    with torch.no_grad():
        for block in sr.blocks:
            block.torgb.weight.zero_()
    return sr


def synthesize(sr: SuperResolution, features: Tensor) -> Tensor:
    """The SR's blocks on features (B, C, h, w) of any size (crops included; ``SuperResolution.forward``
    would resize them to its input resolution) -> (B, 3, h·scale, w·scale)."""
    x, img = features, features[:, :3]
    w = sr.w_const.to(x.dtype).unsqueeze(0)
    for block in sr.blocks:
        x, img = block(x, img, w)
    return img


def _batch(pairs: PairSet, cfg: FitConfig, step: int) -> tuple[Tensor, Tensor]:
    """Step ``step``'s crops: (B, 32, c, c) features and (B, 3, c·s, c·s) targets, a pure function of
    ``(cfg.seed, step)`` (so a resumed fit draws what the uninterrupted one would). With ``train_on``
    ``both``, the first half of the batch reads the student's raw renders, the rest the teacher's."""
    g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    n, c, s, r, b = len(pairs), cfg.crop, cfg.scale, cfg.raw_resolution, cfg.batch_size
    index = torch.randint(n, (b,), generator=g).tolist()
    offsets = torch.randint(r - c + 1, (b, 2), generator=g).tolist()
    flips = (torch.rand(b, generator=g) < 0.5).tolist()
    if cfg.train_on == "both":
        sources = [pairs.features if k < (b + 1) // 2 else pairs.teacher_features for k in range(b)]
    else:
        sources = [pairs.features if cfg.train_on == "student" else pairs.teacher_features] * b
    xs, ys = [], []
    for i, (oy, ox), flip, feats in zip(index, offsets, flips, sources, strict=True):
        x = torch.from_numpy(feats[i, :, oy : oy + c, ox : ox + c].astype(np.float32))
        y = torch.from_numpy(
            pairs.target[i, :, oy * s : (oy + c) * s, ox * s : (ox + c) * s].astype(np.float32)
        )
        if flip:
            x, y = x.flip(-1), y.flip(-1)
        xs.append(x)
        ys.append(y)
    return torch.stack(xs), torch.stack(ys)


def _lr(cfg: FitConfig, step: int) -> float:
    """Step ``step``'s learning rate: ``cfg.lr`` decayed by lp3d's cosine to ``cfg.lr_final_factor``."""
    return cfg.lr * cosine_decay(step, max(cfg.steps, 1), cfg.lr_final_factor)


@torch.no_grad()
def score(sr: SuperResolution, pairs: PairSet) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Held-out scores against the teacher's image: of the SR image and of the bilinearly upsampled raw
    render, for the student's raw renders (``superres_*``, ``bilinear_*``, ``gain_db``) and for the
    teacher's own low-resolution ones (``teacher_*``), and of the student rendered directly at the
    output size (``direct_*``, when the pairs have it: what ``--raw --resolution R_out`` draws); and,
    per pair, a figure row (student: upsampled raw | SR [| direct]; teacher low: upsampled raw | SR;
    teacher's image) as (H, 5W or 6W, 3) uint8."""
    from lp3d.images import rgb_to_uint8

    sr.eval()
    rows: list[np.ndarray] = []
    out: dict[str, list[float]] = {}
    for i in range(len(pairs)):
        y = torch.from_numpy(pairs.target[i : i + 1].astype(np.float32))
        images = []
        for prefix, feats in (("", pairs.features), ("teacher_", pairs.teacher_features)):
            x = torch.from_numpy(feats[i : i + 1].astype(np.float32))
            up = F.interpolate(x[:, :3], size=y.shape[-2:], mode="bilinear", align_corners=False)
            high = sr(x)
            for name, img in (("bilinear", up), ("superres", high)):
                out.setdefault(f"{prefix}{name}_psnr", []).append(float(psnr(img, y)[0]))
                out.setdefault(f"{prefix}{name}_ssim", []).append(float(ssim(img.clamp(-1, 1), y)[0]))
            images += [up, high]
            if not prefix and pairs.direct is not None:
                direct = torch.from_numpy(pairs.direct[i : i + 1].astype(np.float32))
                out.setdefault("direct_psnr", []).append(float(psnr(direct, y)[0]))
                out.setdefault("direct_ssim", []).append(float(ssim(direct.clamp(-1, 1), y)[0]))
                images.append(direct)
        rows.append(np.concatenate([rgb_to_uint8(t[0].numpy()) for t in (*images, y)], axis=1))
    report: dict[str, Any] = {k: float(np.mean(v)) for k, v in out.items()}
    report["gain_db"] = report["superres_psnr"] - report["bilinear_psnr"]
    report["teacher_gain_db"] = report["teacher_superres_psnr"] - report["teacher_bilinear_psnr"]
    report["pairs"] = len(pairs)
    report["per_pair"] = out
    return report, rows


def _train_step(
    sr: SuperResolution,
    opt: torch.optim.Optimizer,
    cfg: FitConfig,
    train: PairSet,
    step: int,
    perceptual: SSIMGradientLoss,
) -> tuple[float, list[float]]:
    """One optimiser step (index ``step``); returns its learning rate and ``[loss, l1, ssim_grad]``."""
    lr = _lr(cfg, step)
    for group in opt.param_groups:
        group["lr"] = lr
    x, y = _batch(train, cfg, step)
    pred = synthesize(sr, x)
    l1 = (pred - y).abs().mean()
    perc = perceptual(pred, y) if cfg.perceptual_weight > 0 else pred.new_zeros(())
    loss = l1 + cfg.perceptual_weight * perc
    if not torch.isfinite(loss):
        raise FitError(f"non-finite loss at step {step} (lr {lr:g}); lower --lr")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return lr, [loss.item(), l1.item(), perc.item()]


def train_steps(
    sr: SuperResolution,
    opt: torch.optim.Optimizer,
    cfg: FitConfig,
    train: PairSet,
    start: int,
    log_path: Path,
    checkpoint: Callable[[int], Any],
    *,
    progress: bool = True,
) -> None:
    """Steps ``start`` … ``cfg.steps - 1`` on crops of ``train``: a row of ``log_path`` (CSV, started
    afresh when ``start`` is 0) per step, and ``checkpoint(steps done)`` every ``cfg.checkpoint_every``
    steps before the last (the caller writes the final checkpoint with the report)."""
    perceptual = SSIMGradientLoss()
    new_log = not log_path.exists() or start == 0
    t0 = time.perf_counter()
    sr.train()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=start, desc="fitting SR", unit="step", file=sys.stderr)
    with open(log_path, "w" if new_log else "a", newline="") as log_file:
        log = csv.writer(log_file)
        if new_log:
            log.writerow(["step", "loss", "l1", "ssim_grad", "lr", "seconds"])
        for step in range(start, cfg.steps):
            lr, values = _train_step(sr, opt, cfg, train, step, perceptual)
            done_steps = step + 1
            log.writerow(
                [done_steps, *(f"{v:.5f}" for v in values), f"{lr:.3g}"] + [f"{time.perf_counter() - t0:.1f}"]
            )
            if bar is not None:
                bar.update()
                bar.set_postfix_str(f"loss {values[0]:.4f}")
            if done_steps % cfg.checkpoint_every == 0 and done_steps < cfg.steps:
                log_file.flush()
                checkpoint(done_steps)
        if bar is not None:
            bar.close()
