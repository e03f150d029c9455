"""The held-out views of a training run, a base class of :class:`lp3d.training.trainer.Trainer`:
the learning curve (:meth:`HeldoutViews.heldout_metrics`, appended to ``heldout.csv`` by
:meth:`~HeldoutViews.log_heldout`) and the sample sheets (``samples/step-NNNNNN.png``,
:meth:`~HeldoutViews.save_samples`). ``Trainer.__init__`` sets up the state these methods use.

May import the modules of :mod:`lp3d.training` before it (``config`` to ``steps``), not ``trainer``
or ``cli``."""

from __future__ import annotations

import csv
import dataclasses
import statistics
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from lp3d.atomic import atomic_path
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.student import render_teacher, render_views
from lp3d.training.synthetic_data import SyntheticDataset, teacher_fingerprint


class HeldoutViews:
    """The held-out learning curve and sample sheets of :class:`~lp3d.training.trainer.Trainer` (its
    base)."""

    # -- held-out curve ----------------------------------------------------------------------------
    @torch.no_grad()
    def heldout_metrics(self) -> dict[str, float]:
        """The learning curve's point: novel-view RGB PSNR of ``heldout_identities`` held-out
        identities (seeds from ``eval_seed_start``) against their own teacher and against the other
        held-out identities' teachers, and the difference (identity specificity, 0 dB for a student
        that ignores its input). Raw renders at ``raw_resolution`` from yaw -30° and +30° (pitch 10°);
        the teacher is the training teacher (``lp3d eval`` scores against the native one)."""
        from lp3d.render.camera import look_at_camera

        cfg = self.config
        if self.heldout is None:
            key = dataclasses.replace(
                self.dataset_key(),
                first_seed=cfg.eval_seed_start,
                n_identities=cfg.heldout_identities,
                teacher_fingerprint=teacher_fingerprint(self.teacher, cfg.eval_seed_start),
            )
            self.heldout = SyntheticDataset.open(
                key, self.teacher, self._input_renderer(), root=self.data_cache, progress=False
            )
        ds = self.heldout
        n = len(ds)
        cams = torch.tensor(
            np.stack([look_at_camera(yaw_deg=y, pitch_deg=10.0) for y in (-30.0, 30.0)]), dtype=torch.float32
        ).to(self.device)
        v = cams.shape[0]
        was_training = self.student.training
        self.student.eval()
        if self._heldout_truth is None:  # the teacher's views never change: render them once per run
            self._heldout_truth = [
                render_views(
                    torch.from_numpy(ds.planes[i : i + 1].astype(np.float32))
                    .to(self.device)
                    .expand(v, -1, -1, -1, -1),
                    self.teacher_decoder,
                    cams,
                    cfg,
                    self.scene,
                )["rgb"]
                for i in range(n)
            ]
        teacher = self._heldout_truth
        student = []
        dec = self.student.decoder.weights()
        for i in range(n):
            image = torch.from_numpy(ds.ref_image[i : i + 1].astype(np.float32)).to(self.device)
            pred = self.student.encode(image)
            student.append(render_views(pred.expand(v, -1, -1, -1, -1), dec, cams, cfg, self.scene)["rgb"])
        self.student.train(was_training)

        def psnr(a: Tensor, b: Tensor) -> float:  # images in [-1, 1]: peak-to-peak 2
            return float(10 * torch.log10(4.0 / (a - b).square().mean().clamp_min(1e-12)))

        own = [psnr(student[i], teacher[i]) for i in range(n)]
        other = [statistics.fmean(psnr(student[i], teacher[j]) for j in range(n) if j != i) for i in range(n)]
        return {
            "psnr_own": statistics.fmean(own),
            "psnr_other": statistics.fmean(other),
            "specificity_db": statistics.fmean(own) - statistics.fmean(other),
        }

    def log_heldout(self) -> dict[str, float]:
        """Append :meth:`heldout_metrics` at the current step to ``heldout.csv`` (the learning curve)."""
        m = self.heldout_metrics()
        path = self.out_dir / "heldout.csv"
        rows: list[dict[str, str]] = []
        if path.exists():
            with open(path, newline="") as f:
                rows = [
                    r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) < self.step
                ]
        rows.append({"step": str(self.step), **{k: f"{v:.4f}" for k, v in m.items()}})
        self._tensorboard().heldout(self.step, m)
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, ["step", "psnr_own", "psnr_other", "specificity_db"])
            w.writeheader()
            w.writerows(rows)
        return m

    # -- previews ----------------------------------------------------------------------------------
    @torch.no_grad()
    def save_samples(
        self, seeds: Sequence[int] | None = None, yaws: Sequence[float] = (-30.0, 0.0, 30.0)
    ) -> Path:
        """``samples/step-NNNNNN.png``: per held-out identity, a teacher row (input, views at ``yaws``)
        and a student row (its input-view render, the same views)."""
        from lp3d.images import rgb_to_uint8, save_png, tile
        from lp3d.render.camera import look_at_camera

        cfg = self.config
        seeds = list(seeds) if seeds is not None else [cfg.eval_seed_start, cfg.eval_seed_start + 1]
        rng = np.random.Generator(np.random.PCG64(12345))  # fixed preview cameras, independent of training
        self.student.eval()
        images: list[np.ndarray] = []
        views = torch.tensor(np.stack([look_at_camera(yaw_deg=y) for y in yaws]), dtype=torch.float32)
        views = views.to(self.device)
        for seed in seeds:
            planes = self._teacher_planes([self.teacher.sample(seed)])
            cam = (
                torch.from_numpy(sample_cameras(cfg.reference_cameras, 1, rng).labels).float().to(self.device)
            )
            _, _, image = render_teacher(
                self.teacher, planes, self.teacher_decoder, cam, cfg, self.scene, raw=False
            )
            _, _, t_views = render_teacher(
                self.teacher,
                planes.expand(len(yaws), -1, -1, -1, -1),
                self.teacher_decoder,
                views,
                cfg,
                self.scene,
                raw=False,
            )
            assert image is not None and t_views is not None
            pred = self.student.encode(image)
            s_in = self.student.render(pred, cam).high
            s_views = self.student.render(pred.expand(len(yaws), -1, -1, -1, -1), views).high
            images += [rgb_to_uint8(image[0].cpu().numpy())] + [
                rgb_to_uint8(v.cpu().numpy()) for v in t_views
            ]
            images += [rgb_to_uint8(s_in[0].cpu().numpy())] + [rgb_to_uint8(v.cpu().numpy()) for v in s_views]
        self.student.train()
        sheet = tile(images, 1 + len(yaws))
        self._tensorboard().samples(self.step, sheet)
        return save_png(self.out_dir / "samples" / f"step-{self.step:06d}.png", sheet)
