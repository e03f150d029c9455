"""The held-out views of a training run (:class:`HeldoutViews`, a part of
:class:`lp3d.training.trainer.Trainer`): the learning curve (:meth:`HeldoutViews.metrics`, appended
to ``heldout.csv`` by :meth:`~HeldoutViews.log`) and the sample sheets (``samples/step-NNNNNN.png``,
:meth:`~HeldoutViews.save_samples`).

May import the modules of :mod:`lp3d.training` before it (``config`` to ``steps``, ``run_teacher``),
not ``trainer`` or ``cli``."""

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
from lp3d.render.psnr import psnr
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.run_teacher import RunTeacher
from lp3d.training.student import Student, render_views
from lp3d.training.synthetic_data import SyntheticDataset, teacher_fingerprint
from lp3d.training.tensorboard_log import TensorBoardLog

__all__ = ["HeldoutViews"]

#: ``heldout.csv``'s columns.
HELDOUT_COLUMNS = ["step", "psnr_own", "psnr_other", "specificity_db"]


class HeldoutViews:
    """The held-out learning curve and sample sheets of a run whose ``student`` learns from
    ``teacher``, written into the run directory ``out_dir``. The held-out identities' dataset is
    opened (synthesised the first time) and their teacher views rendered at first use."""

    def __init__(self, teacher: RunTeacher, student: Student, out_dir: Path) -> None:
        self.teacher = teacher
        self.student = student
        self.out_dir = Path(out_dir)
        self.dataset: SyntheticDataset | None = None
        self._truth: list[Tensor] | None = None  # the teacher's views never change: rendered once

    def open_dataset(self) -> SyntheticDataset:
        """The held-out identities (``heldout_identities`` seeds from ``eval_seed_start``): planes and
        input renders, cached like the training set."""
        if self.dataset is None:
            cfg, teacher = self.teacher.config, self.teacher.teacher
            key = dataclasses.replace(
                self.teacher.dataset_key(),
                first_seed=cfg.eval_seed_start,
                n_identities=cfg.heldout_identities,
                teacher_fingerprint=teacher_fingerprint(teacher, cfg.eval_seed_start),
            )
            self.dataset = self.teacher.open_dataset(key, progress=False)
        return self.dataset

    # -- held-out curve ----------------------------------------------------------------------------
    @torch.no_grad()
    def metrics(self) -> dict[str, float]:
        """The learning curve's point: novel-view RGB PSNR of ``heldout_identities`` held-out
        identities (seeds from ``eval_seed_start``) against their own teacher and against the other
        held-out identities' teachers, and the difference (identity specificity, 0 dB for a student
        that ignores its input). Raw renders at ``raw_resolution`` from yaw -30° and +30° (pitch 10°);
        the teacher is the training teacher (``lp3d eval`` scores against the native one). Each
        pair's score is the mean PSNR of its views, in lp3d's one PSNR (:func:`lp3d.render.psnr.psnr`,
        the evaluation's)."""
        from lp3d.render.camera import look_at_camera

        cfg, device, scene = self.teacher.config, self.teacher.device, self.teacher.scene
        ds = self.open_dataset()
        n = len(ds)
        cams = torch.tensor(
            np.stack([look_at_camera(yaw_deg=y, pitch_deg=10.0) for y in (-30.0, 30.0)]), dtype=torch.float32
        ).to(device)
        v = cams.shape[0]
        was_training = self.student.training
        self.student.eval()
        if self._truth is None:
            self._truth = [
                render_views(
                    torch.from_numpy(ds.planes[i : i + 1].astype(np.float32))
                    .to(device)
                    .expand(v, -1, -1, -1, -1),
                    self.teacher.decoder,
                    cams,
                    cfg,
                    scene,
                )["rgb"]
                for i in range(n)
            ]
        teacher = self._truth
        student = []
        dec = self.student.decoder.weights()
        for i in range(n):
            image = torch.from_numpy(ds.ref_image[i : i + 1].astype(np.float32)).to(device)
            pred = self.student.encode(image)
            student.append(render_views(pred.expand(v, -1, -1, -1, -1), dec, cams, cfg, scene)["rgb"])
        self.student.train(was_training)

        def score(a: Tensor, b: Tensor) -> float:
            return float(psnr(a, b).mean())

        own = [score(student[i], teacher[i]) for i in range(n)]
        other = [
            statistics.fmean(score(student[i], teacher[j]) for j in range(n) if j != i) for i in range(n)
        ]
        return {
            "psnr_own": statistics.fmean(own),
            "psnr_other": statistics.fmean(other),
            "specificity_db": statistics.fmean(own) - statistics.fmean(other),
        }

    def log(self, step: int, tensorboard: TensorBoardLog) -> dict[str, float]:
        """Append :meth:`metrics` at ``step`` to ``heldout.csv`` (the learning curve; rows of later
        steps, from a run continued from an older checkpoint, are dropped) and to ``tensorboard``."""
        m = self.metrics()
        path = self.out_dir / "heldout.csv"
        rows: list[dict[str, str]] = []
        if path.exists():
            with open(path, newline="") as f:
                rows = [r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) < step]
        rows.append({"step": str(step), **{k: f"{v:.4f}" for k, v in m.items()}})
        tensorboard.heldout(step, m)
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, HELDOUT_COLUMNS)
            w.writeheader()
            w.writerows(rows)
        return m

    # -- previews ----------------------------------------------------------------------------------
    @torch.no_grad()
    def save_samples(
        self,
        step: int,
        tensorboard: TensorBoardLog,
        seeds: Sequence[int] | None = None,
        yaws: Sequence[float] = (-30.0, 0.0, 30.0),
    ) -> Path:
        """``samples/step-NNNNNN.png`` (and ``tensorboard``'s sheet): per held-out identity, a teacher
        row (input, views at ``yaws``) and a student row (its input-view render, the same views)."""
        from lp3d.images import rgb_to_uint8, save_png, tile
        from lp3d.render.camera import look_at_camera

        cfg, device, teacher = self.teacher.config, self.teacher.device, self.teacher
        seeds = list(seeds) if seeds is not None else [cfg.eval_seed_start, cfg.eval_seed_start + 1]
        rng = np.random.Generator(np.random.PCG64(12345))  # fixed preview cameras, independent of training
        self.student.eval()
        images: list[np.ndarray] = []
        views = torch.tensor(np.stack([look_at_camera(yaw_deg=y) for y in yaws]), dtype=torch.float32)
        views = views.to(device)
        for seed in seeds:
            planes = teacher.planes([teacher.teacher.sample(seed)])
            cam = torch.from_numpy(sample_cameras(cfg.reference_cameras, 1, rng).labels).float().to(device)
            _, _, image = teacher.render(planes, cam, raw=False)
            _, _, t_views = teacher.render(planes.expand(len(yaws), -1, -1, -1, -1), views, raw=False)
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
        tensorboard.samples(step, sheet)
        return save_png(self.out_dir / "samples" / f"step-{step:06d}.png", sheet)
