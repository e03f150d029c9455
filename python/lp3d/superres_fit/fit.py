"""Fit a super-resolution network (SR) for a trained encoder whose recipe has none.

The paper's recipe trains an SR with the encoder (EG3D's, paper Eq. 2); the CPU recipe
(``python -m lp3d.train --config small``, the shipped model) renders its final image directly and
trains none. This module gives such a model one, with the encoder and decoder frozen::

    lp3d superres-fit [MODEL] --out runs/sr-small       # or python -m lp3d.superres_fit
    lp3d export --superres runs/sr-small/superres-fit.pt --package MODEL.onnx [--weights MODEL.pt]

``MODEL`` is anything ``lp3d encode --model`` takes (default: the shipped model).

1. **Pairs, made once.** For each of ``identities`` procedural-teacher identities (seeds from
   ``first_seed``, inside the training range but past any CPU dataset, and disjoint from
   ``lp3d.evaluation``'s held-out seeds): the teacher renders the encoder's input from a reference camera
   (:data:`~lp3d.training.camera_sampling.FFHQ_REFERENCE`), the model encodes it, and for ``views`` multiview
   cameras (:data:`~lp3d.training.camera_sampling.FFHQ_MULTIVIEW`) ``lp3d_render`` draws the *student's* raw
   feature image at ``raw_resolution``, the *teacher's* image at ``output_resolution``, and the
   teacher's own raw feature image at ``raw_resolution`` from its head at the student's plane
   resolution (the well-posed pairs EG3D's SR learns from: the same head, low and high). The pairs
   (and ``heldout_identities`` more, from ``heldout_first_seed``) are cached on disk in a folder named
   by a hash of everything they depend on (:class:`PairKey`: the model's weights, the teacher's
   fingerprint, seeds, sizes, samples, cameras); ``meta.json`` records each array's SHA-256, and a
   folder that does not match (edited, truncated, another key) is reported and rebuilt, never used.
2. **Training.** Only the 2-D SR learns (EG3D's architecture with the paper's constant w,
   :class:`lp3d.nets.superres.SuperResolution`): random crops of ``crop``² raw pixels and their teacher
   crops, horizontal flips, L1 + ``ssim-grad`` (the CPU configurations' perceptual loss), Adam with a
   cosine decay. ``train_on`` picks the inputs: ``student`` (its raw renders, mapped to the teacher's
   image: the SR also learns to correct the student, which it mostly cannot), ``teacher`` (the
   teacher's own low-resolution renders: pure super-resolution of the decoder's feature images), or
   ``both`` (the default: half of each batch each). Each ToRGB layer starts at zero, so the network
   starts as FIR upsampling of the raw rgb (about the bilinear baseline) and learns a residual; the
   learning rate is high (1e-2) for a short fit. A checkpoint is written atomically every
   ``checkpoint_every`` steps and at the end; rerunning the same command resumes it.
3. **Held-out score.** PSNR and SSIM of the SR image of the student's raw render against the
   teacher's image on the held-out pairs, beside the same for the student's raw render upsampled
   bilinearly (what the SR must beat to be worth shipping), and the same two for the teacher's own
   low-resolution renders (``teacher_*``); ``report.json`` and ``heldout.png`` (student: upsampled
   raw | SR; teacher's low-resolution head: upsampled raw | SR; the teacher's image) in ``--out``.

The checkpoint (``superres-fit.pt``, ``"format": "lp3d-superres-fit-v1"``) is a plain dict of
tensors and JSON strings (``torch.load(weights_only=True)``); :func:`load_fit` reads it and
``lp3d export --superres`` packages it as ONNX beside the encoder.

This module holds :func:`fit_superres` (the steps above, in order) and the command line; the parts live
in :mod:`~lp3d.superres_fit.config` (:class:`FitConfig`), :mod:`~lp3d.superres_fit.data`
(the cached pairs), :mod:`~lp3d.superres_fit.train` (training and the held-out score) and
:mod:`~lp3d.superres_fit.checkpoint` (:func:`load_fit`), and are re-exported here.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from lp3d.atomic import atomic_path
from lp3d.nets.superres import SuperResolution
from lp3d.superres_fit.checkpoint import (
    CHECKPOINT_NAME,
    FIT_FORMAT,
    fit_checkpoint,
    load_fit,
    save_fit_checkpoint,
)
from lp3d.superres_fit.config import FitConfig, FitError
from lp3d.superres_fit.data import (
    PairKey,
    PairSet,
    StalePairsError,
    default_pair_cache,
    model_fingerprint,
    pair_keys,
)
from lp3d.superres_fit.train import new_superres, score, train_steps

__all__ = [
    "FIT_FORMAT",
    "FitConfig",
    "FitError",
    "FitResult",
    "PairKey",
    "PairSet",
    "StalePairsError",
    "default_pair_cache",
    "fit_superres",
    "load_fit",
    "load_model",
    "model_fingerprint",
    "open_pairs",
]


@dataclass
class FitResult:
    """What :func:`fit_superres` made: the network, its checkpoint and the held-out report."""

    superres: SuperResolution
    checkpoint: Path
    report: dict[str, Any]


def fit_superres(
    model: str | os.PathLike[str] | None,
    out: str | os.PathLike[str],
    cfg: FitConfig | None = None,
    *,
    backend: str | None = None,
    cache: str | os.PathLike[str] | None = None,
    progress: bool = True,
) -> FitResult:
    """Fit an SR for ``model`` (default: the shipped model) into ``out``; see the module docstring.
    Resumes ``out/superres-fit.pt`` when it exists for the same configuration and model."""
    cfg = cfg or FitConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / CHECKPOINT_NAME
    encoder, info = load_model(model, backend)
    sr = new_superres(cfg)
    opt = torch.optim.Adam(sr.parameters(), lr=cfg.lr, betas=(0.9, 0.99))
    start, report = _resume(ckpt_path, cfg, info, sr, opt)
    train, heldout, t_pairs = open_pairs(cfg, encoder, cache, progress)
    pair_info = {"train": str(train.path), "heldout": str(heldout.path)}

    def save(step: int, report: dict[str, Any] | None) -> None:
        save_fit_checkpoint(fit_checkpoint(sr, opt, cfg, step, info, pair_info, report), ckpt_path)

    t0 = time.perf_counter()
    if start < cfg.steps:
        train_steps(
            sr, opt, cfg, train, start, out / "log.csv", lambda step: save(step, None), progress=progress
        )
        report = None
    t_train = time.perf_counter() - t0
    if report is None:
        report, rows = score(sr, heldout)
        report.update(
            {
                "steps": cfg.steps,
                "training_pairs": len(train),
                "train_seconds_this_run": round(t_train, 1),
                "pairs_seconds_this_run": round(t_pairs, 1),
            }
        )
        save(cfg.steps, report)
        _write_report(out, rows, cfg, info, report)
    _print_report(report, cfg, ckpt_path)
    return FitResult(sr.eval(), ckpt_path, report)


def load_model(model: str | os.PathLike[str] | None, backend: str | None) -> tuple[Any, dict[str, Any]]:
    """The encoder of ``model`` (default: the shipped model) and what the checkpoint records of it."""
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
    from lp3d.lift.model_package import decoder_digest

    model_path = Path(model) if model is not None else DEFAULT_MODEL
    encoder = load_encoder(model_path, backend)  # type: ignore[arg-type]
    pkg = encoder.package
    info = {
        "path": str(model_path.resolve()),
        "fingerprint": model_fingerprint(encoder),
        "decoder_sha256": decoder_digest(pkg.decoder),
        "config_name": pkg.config_name,
        "image_size": pkg.image_size,
        "teacher": "procedural",
    }
    return encoder, info


def _resume(
    ckpt_path: Path, cfg: FitConfig, info: dict[str, Any], sr: SuperResolution, opt: torch.optim.Optimizer
) -> tuple[int, dict[str, Any] | None]:
    """Load ``ckpt_path`` into ``sr`` and ``opt`` when it exists; ``(step, report)`` to go on from
    (``(0, None)`` for a new fit). A checkpoint of another configuration or model is a :class:`FitError`."""
    if not ckpt_path.exists():
        return 0, None
    done = load_fit(ckpt_path)
    if done.config != cfg:
        changed = [
            f"{k}: {v!r} -> {getattr(cfg, k)!r}"
            for k, v in done.config.to_dict().items()
            if v != cfg.to_dict()[k]
        ]
        raise FitError(
            f"{ckpt_path} was made with another configuration ({'; '.join(changed)}); use another --out"
        )
    if done.model.get("fingerprint") != info["fingerprint"]:
        raise FitError(
            f"{ckpt_path} was fitted for another model ({done.model.get('path')}); use another --out"
        )
    sr.load_state_dict(done.superres.state_dict())
    opt.load_state_dict(done.raw["optimizer"])
    start, report = done.step, done.report
    print(f"resuming {ckpt_path} at step {start} of {cfg.steps}")
    return start, report


def open_pairs(
    cfg: FitConfig, encoder: Any, cache: str | os.PathLike[str] | None, progress: bool
) -> tuple[PairSet, PairSet, float]:
    """The training and held-out pairs (cached or rendered now) and the seconds that took."""
    from lp3d.teachers import ProceduralTeacher

    teacher = ProceduralTeacher(resolution=cfg.teacher_resolution)
    train_key, heldout_key = pair_keys(cfg, encoder, teacher)
    t0 = time.perf_counter()
    train = PairSet.open(train_key, encoder, teacher, root=cache, progress=progress)
    heldout = PairSet.open(heldout_key, encoder, teacher, root=cache, progress=progress)
    t_pairs = time.perf_counter() - t0
    print(
        f"pairs: {len(train)} training ({train_key.identities} identities × {train_key.views} views), "
        f"{len(heldout)} held-out; {cfg.raw_resolution}² raw -> {cfg.output_resolution}²; "
        f"ready in {t_pairs:.0f} s ({train.path.parent})"
    )
    return train, heldout, t_pairs


def _write_report(
    out: Path, rows: list[Any], cfg: FitConfig, info: dict[str, Any], report: dict[str, Any]
) -> None:
    """``heldout.png`` (the first four held-out figure rows) and ``report.json`` in ``out``."""
    from lp3d.images import save_png, tile

    save_png(out / "heldout.png", tile(rows[:4], columns=1))
    with atomic_path(out / "report.json") as tmp:
        tmp.write_text(json.dumps({"config": cfg.to_dict(), "model": info, **report}, indent=2) + "\n")


def _print_report(report: dict[str, Any], cfg: FitConfig, ckpt_path: Path) -> None:
    """The held-out scores, a warning when the SR does not beat bilinear upsampling, and what to run next."""
    print(
        f"held-out, the teacher's own low-resolution renders: SR {report['teacher_superres_psnr']:.2f} dB, "
        f"bilinear {report['teacher_bilinear_psnr']:.2f} dB ({report['teacher_gain_db']:+.2f} dB)"
    )
    print(
        f"held-out ({report['pairs']} pairs): SR {report['superres_psnr']:.2f} dB PSNR / SSIM "
        f"{report['superres_ssim']:.3f}; bilinear upsampling of the raw render "
        f"{report['bilinear_psnr']:.2f} dB / {report['bilinear_ssim']:.3f}; gain {report['gain_db']:+.2f} dB"
    )
    if "direct_psnr" in report:
        print(
            f"  (the student rendered directly at {cfg.output_resolution}²: {report['direct_psnr']:.2f} dB / "
            f"{report['direct_ssim']:.3f})"
        )
    if report["gain_db"] <= 0:
        print(
            "warning: the SR does not beat bilinear upsampling on the held-out pairs; do not ship it",
            file=sys.stderr,
        )
    print(f"wrote {ckpt_path}; package it with: lp3d export --superres {ckpt_path} --package MODEL.onnx")
