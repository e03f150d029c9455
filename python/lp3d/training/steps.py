"""The per-step work of a training run (:class:`TrainingSteps`, a part of
:class:`lp3d.training.trainer.Trainer` built with exactly what a step uses): the data (the paper
recipe's synthesised :class:`Batch`, the CPU recipe's cached dataset), one training step of either
recipe with its loss, gradient average and optimiser step, and the discriminator step.

May import the modules of :mod:`lp3d.training` before it (``config`` to ``optim``, ``run_teacher``),
not ``heldout``, ``trainer`` or ``cli``."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lp3d.nets.discriminator import DualDiscriminator, d_loss, r1_penalty
from lp3d.render.torch_twin import rays_from_cameras, render_rays
from lp3d.render.triplane import mirror_planes
from lp3d.training import distributed
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.config import TrainConfig
from lp3d.training.losses import DistillationLoss, ViewRenders, l1, normalised_triplane_loss
from lp3d.training.optim import Optimisation
from lp3d.training.run_teacher import RunTeacher
from lp3d.training.student import Student
from lp3d.training.synthetic_data import SyntheticDataset


class NonFiniteError(ValueError):
    """NaN/Inf in a training batch or loss; the message names the step, the tensor and the seeds."""


@dataclass
class Batch:
    """One synthesised batch: teacher planes (B,3,32,T,T), cameras (B,25) and the teacher renders."""

    seeds: list[int]
    planes: Tensor
    ref_cameras: Tensor
    mv_cameras: Tensor
    ref_image: Tensor
    mv: ViewRenders
    ref: ViewRenders | None
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Ranks:
    """This process's place under torchrun: ``rank`` of ``size`` processes (0 of 1 without it)."""

    rank: int = 0
    size: int = 1

    def shard(self, x: Any) -> Any:
        """This rank's rows of a global batch (everything in one process)."""
        return distributed.shard(x, rank_=self.rank, size=self.size)


@dataclass(eq=False)
class TrainingSteps:
    """One training step of either recipe (:meth:`run`) and the paper recipe's batches
    (:meth:`synthesize`), built with what they use: the run's ``config``, its ``teacher``, the
    ``student`` and ``discriminator`` they train with ``optimisation`` and ``losses``, the seeded
    ``data_rng`` every batch is drawn from, this process's ``ranks``, whether the encoder runs under
    ``amp``, whether the student's SR came ``pretrained_sr`` from the teacher, and for the CPU
    recipe its ``dataset`` and the channel scales ``plane_scale`` of its triplanes. The objects are
    the trainer's (a checkpoint restores them in place); the step index is passed in."""

    config: TrainConfig
    teacher: RunTeacher
    student: Student
    discriminator: DualDiscriminator
    optimisation: Optimisation
    losses: DistillationLoss
    data_rng: np.random.Generator
    ranks: Ranks = field(default_factory=Ranks)
    amp: bool = False
    pretrained_sr: bool = False
    dataset: SyntheticDataset | None = None
    plane_scale: Tensor | None = None

    @property
    def local_batch(self) -> int:
        """This rank's share of the global batch."""
        return self.config.batch_size // self.ranks.size

    def set_trainable(self, step: int) -> None:
        """Stage 1 freezes the decoder, and the SR when it came pretrained (supplement, "Training")."""
        if self.config.recipe == "cpu":  # the teacher's decoder is kept; there is no SR to train
            self.student.decoder.requires_grad_(False)
            self.student.superres.requires_grad_(False)
            return
        stage2 = self.config.stage(step) == 2
        self.student.decoder.requires_grad_(stage2)
        self.student.superres.requires_grad_(stage2 or not self.pretrained_sr)

    def synthesize(self, step: int) -> Batch:
        """Identities, cameras and teacher renders of ``step`` (all randomness from ``data_rng``).

        Under torchrun the whole global batch is drawn and this rank keeps its rows (``shard``), so the
        stream does not depend on the number of processes; only this rank's rows are rendered."""
        cfg, teacher, device = self.config, self.teacher, self.teacher.device
        b = cfg.batch_size
        seeds = [int(s) for s in self.data_rng.integers(cfg.train_seeds[0], cfg.train_seeds[1], size=b)]
        ref_labels = sample_cameras(cfg.reference_cameras, b, self.data_rng).labels
        mv_labels = sample_cameras(cfg.multiview_cameras, b, self.data_rng).labels
        seeds, ref_labels, mv_labels = (self.ranks.shard(x) for x in (seeds, ref_labels, mv_labels))
        ref_cams = torch.from_numpy(np.ascontiguousarray(ref_labels))
        mv_cams = torch.from_numpy(np.ascontiguousarray(mv_labels))
        ref_cams = ref_cams.to(device, torch.float32)
        mv_cams = mv_cams.to(device, torch.float32)
        planes = teacher.planes(teacher.teacher.sample_batch(seeds))
        is_ref = cfg.reference_step(step)
        f_ref, d_ref, ref_image = teacher.render(planes, ref_cams, raw=is_ref, high=True)
        f_mv, d_mv, h_mv = teacher.render(planes, mv_cams)
        assert ref_image is not None and f_mv is not None and d_mv is not None and h_mv is not None
        ref = None
        if is_ref:
            assert f_ref is not None and d_ref is not None
            ref = ViewRenders(features=f_ref, high=ref_image, depth=d_ref)
        batch = Batch(
            seeds=seeds,
            planes=planes,
            ref_cameras=ref_cams,
            mv_cameras=mv_cams,
            ref_image=ref_image,
            mv=ViewRenders(features=f_mv, high=h_mv, depth=d_mv),
            ref=ref,
        )
        self.check_batch(batch, step)
        return batch

    def check_batch(self, batch: Batch, step: int) -> None:
        """Raise :class:`NonFiniteError` / ValueError naming the first bad tensor of a batch (this
        rank's share of it under torchrun)."""
        cfg = self.config
        b, s, r = self.local_batch, cfg.image_size, cfg.raw_resolution
        t = cfg.triplane_resolution
        expected: list[tuple[str, Tensor, tuple[int, ...]]] = [
            ("teacher triplanes", batch.planes, (b, 3, cfg.encoder.plane_channels, -1, -1)),
            ("reference image (encoder input)", batch.ref_image, (b, 3, s, s)),
            ("multiview feature image I_f", batch.mv.features, (b, cfg.superres.in_channels, r, r)),
            ("multiview high-resolution image", batch.mv.high, (b, 3, s, s)),
            ("multiview depth I_D", batch.mv.depth, (b, r, r)),
        ]
        if batch.ref is not None:
            expected += [
                ("reference feature image I_f", batch.ref.features, (b, cfg.superres.in_channels, r, r)),
                ("reference depth I_D", batch.ref.depth, (b, r, r)),
            ]
        for name, x, shape in expected:
            if x.ndim != len(shape) or any(
                want not in (-1, got) for want, got in zip(shape, x.shape, strict=True)
            ):
                raise ValueError(
                    f"step {step}: the teacher's {name} has shape {tuple(x.shape)}, expected "
                    f"{tuple('*' if v == -1 else v for v in shape)} (image size {s}, triplane {t})"
                )
            bad = ~torch.isfinite(x.reshape(x.shape[0], -1)).all(dim=1)
            if bool(bad.any()):
                which = [batch.seeds[i] for i in bad.nonzero().flatten().tolist()]
                raise NonFiniteError(
                    f"step {step}: NaN/Inf in the teacher's {name} for identity seed(s) {which}; "
                    "the teacher produced invalid data (nothing was trained on this batch)"
                )

    # -- one step ----------------------------------------------------------------------------------
    def run(self, step: int, batch: Batch | None = None) -> dict[str, Any]:
        """Run step ``step`` (synthesising its batch unless given); returns its log row, whose losses
        under torchrun are their means over the ranks."""
        t0 = time.perf_counter()
        if self.config.recipe == "cpu":
            row = self.cpu_step(step)
        else:
            row = self.paper_step(step, batch)
        self._mean_over_ranks(row)
        row["seconds"] = time.perf_counter() - t0
        return row

    def paper_step(self, step: int, batch: Batch | None = None) -> dict[str, Any]:
        """One step of the paper's recipe on ``batch`` (synthesised for ``step`` unless given):
        Eq. 5, the student's optimiser step and, in stage 2, the discriminator's."""
        cfg = self.config
        stage = cfg.stage(step)
        self.set_trainable(step)
        batch = batch if batch is not None else self.synthesize(step)
        weights = cfg.weights(step)
        is_ref = batch.ref is not None
        b = self.local_batch
        use_d = stage == 2 and (weights.adversarial_reference > 0 or weights.adversarial_multiview > 0)

        self.student.train()
        self.discriminator.requires_grad_(False)
        planes = self.student.encode(batch.ref_image, amp=self.amp)
        row: dict[str, Any] = {"step": step, "stage": stage, "reference": int(is_ref)}
        total = planes.new_zeros(())
        if weights.triplane > 0:
            tri = self.losses.triplane(planes, self.teacher.target_planes(batch.planes))
            total = total + weights.triplane * tri
            row["tri"] = float(tri.detach())
        # One render call for both view sets (one triplane per camera).
        cams = torch.cat([batch.mv_cameras, batch.ref_cameras]) if is_ref else batch.mv_cameras
        rendered = self.student.render(
            torch.cat([planes, planes]) if is_ref else planes, cams, freeze_superres=stage == 1
        )
        disc = self.discriminator if use_d else None
        mv_s = ViewRenders(rendered.features[:b], rendered.high[:b], rendered.depth[:b])
        mv_loss, mv_terms = self.losses.views(mv_s, batch.mv, weights, kind="multiview", discriminator=disc)
        total = total + mv_loss
        row.update({f"mv_{k}": float(v) for k, v in mv_terms.items()})
        if is_ref:
            assert batch.ref is not None
            ref_s = ViewRenders(rendered.features[b:], rendered.high[b:], rendered.depth[b:])
            ref_loss, ref_terms = self.losses.views(
                ref_s, batch.ref, weights, kind="reference", discriminator=disc
            )
            total = total + ref_loss
            row.update({f"ref_{k}": float(v) for k, v in ref_terms.items()})
        if stage == 1 and not self.pretrained_sr:
            # No pretrained SR to freeze: learn one from the teacher's own pairs I_f -> I_high, as
            # EG3D's SR learnt from its generator's renders (the student's loss does not move it).
            sr_weights = dataclasses.replace(
                weights, color_raw=0.0, perceptual_raw=0.0, feature=0.0, depth=0.0, category=0.0
            )
            teacher_sr = ViewRenders(
                batch.mv.features, self.student.superres(batch.mv.features), batch.mv.depth
            )
            sr_loss, sr_terms = self.losses.views(teacher_sr, batch.mv, sr_weights, kind="multiview")
            total = total + sr_loss
            row.update({f"sr_{k}": float(v) for k, v in sr_terms.items()})
        if not bool(torch.isfinite(total)):
            terms = {k: v for k, v in row.items() if isinstance(v, float)}
            raise NonFiniteError(
                f"step {step}: the training loss is {float(total.detach())} (terms {terms}, identity seeds "
                f"{batch.seeds}); resume from the last checkpoint with a lower learning rate"
            )
        self.student_step(total, row)

        if use_d:
            row.update(self.discriminator_step(step, batch, rendered, is_ref))
        return row

    def _mean_over_ranks(self, row: dict[str, Any]) -> None:
        """Under torchrun: the logged losses become their means over the ranks (each is a mean over
        an equal share of the batch, so this is the global batch's mean)."""
        if self.ranks.size > 1:
            row.update(
                distributed.mean_over_ranks(
                    {k: v for k, v in row.items() if isinstance(v, float)}, self.teacher.device
                )
            )

    def student_step(self, total: Tensor, row: dict[str, Any]) -> None:
        """Backward ``total``, average the gradients over the ranks (torchrun), clip, one optimiser and
        scheduler step; logs the loss and rate in ``row``."""
        opt = self.optimisation
        opt.opt_g.zero_grad(set_to_none=True)
        opt.scaler.scale(total).backward()
        distributed.average_gradients(self.student.parameters())
        if self.config.grad_clip > 0:
            opt.scaler.unscale_(opt.opt_g)
            torch.nn.utils.clip_grad_norm_(self.student.parameters(), self.config.grad_clip)
        opt.scaler.step(opt.opt_g)
        opt.scaler.update()
        opt.sched_g.step()
        row["loss"] = float(total.detach())
        row["lr"] = float(opt.opt_g.param_groups[0]["lr"])

    def cpu_step(self, step: int) -> dict[str, Any]:
        """One step of the CPU recipe: a batch of cached identities, normalised L_tri, and after
        ``regression_steps`` the RGB L1 of random rays of their cached teacher views."""
        cfg, ds, device = self.config, self.dataset, self.teacher.device
        assert ds is not None and self.plane_scale is not None
        self.set_trainable(step)
        self.student.train()
        # The global batch's rows and flips, of which this rank keeps its share (torchrun).
        idx = np.sort(self.data_rng.integers(0, len(ds), size=cfg.batch_size))
        flips = self.data_rng.random(len(idx)) < 0.5 if cfg.mirror_augment else None
        idx = self.ranks.shard(idx)
        image = torch.from_numpy(ds.ref_image[idx].astype(np.float32)).to(device)
        target = torch.from_numpy(ds.planes[idx].astype(np.float32)).to(device)
        if flips is not None:  # a flipped input is the mirrored head: twice the identities for free
            flip = torch.from_numpy(np.ascontiguousarray(self.ranks.shard(flips))).to(device)
            image = torch.where(flip[:, None, None, None], image.flip(-1), image)
            target = torch.where(flip[:, None, None, None, None], mirror_planes(target), target)
        planes = self.student.encode(image, amp=self.amp)
        tri = normalised_triplane_loss(planes, target, self.plane_scale)
        total = cfg.triplane_weight * tri
        row: dict[str, Any] = {
            "step": step,
            "stage": 1 if step < cfg.regression_steps else 2,
            "tri": float(tri.detach()),
        }
        if step >= cfg.regression_steps and cfg.rays_per_identity > 0 and cfg.ray_weight > 0:
            pred, want = self.random_ray_rgb(planes, target)
            ray = l1(pred, want, name="ray rgb")
            total = total + cfg.ray_weight * ray
            row["ray"] = float(ray.detach())
        if not bool(torch.isfinite(total)):
            raise NonFiniteError(
                f"step {step}: the training loss is {float(total)} (terms {row}, dataset rows "
                f"{idx.tolist()}); resume from the last checkpoint with a lower learning rate"
            )
        self.student_step(total, row)
        return row

    def random_ray_rgb(self, planes: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
        """RGB (B, M, 3) of the student's planes and of the teacher's ``target`` planes on M random
        pixel rays of one random multiview camera per identity (drawn from ``data_rng`` for the global
        batch, of which this rank keeps its rows)."""
        cfg, device = self.config, self.teacher.device
        b, m, r = cfg.batch_size, cfg.rays_per_identity, cfg.raw_resolution
        cams = torch.from_numpy(
            np.ascontiguousarray(
                self.ranks.shard(sample_cameras(cfg.multiview_cameras, b, self.data_rng).labels)
            )
        )
        pixels = self.data_rng.integers(0, r * r, size=(b, m))
        pixels = torch.from_numpy(np.ascontiguousarray(self.ranks.shard(pixels))).to(device)
        origins, directions = rays_from_cameras(cams.to(device, torch.float32), r)
        gather = pixels.unsqueeze(-1).expand(-1, -1, 3)
        origins, directions = origins.gather(1, gather), directions.gather(1, gather)

        def rgb(p: Tensor, decoder: Sequence[Tensor]) -> Tensor:
            out = render_rays(
                p,
                *decoder,
                origins,
                directions,
                bounds=self.teacher.scene,
                settings=cfg.render_settings(),
            )
            return out["features"][..., :3]

        with torch.no_grad():
            want = rgb(target, self.teacher.decoder)
        return rgb(planes, self.student.decoder.weights()), want

    def discriminator_step(
        self, step: int, batch: Batch, fake: ViewRenders, is_ref: bool
    ) -> dict[str, float]:
        """Teacher renders are real, student renders fake (paper §3.2: no real photographs)."""
        cfg, opt = self.config, self.optimisation
        self.discriminator.requires_grad_(True)
        real_high = torch.cat([batch.mv.high, batch.ref.high]) if is_ref and batch.ref else batch.mv.high
        real_raw = torch.cat([batch.mv.raw, batch.ref.raw]) if is_ref and batch.ref else batch.mv.raw
        loss = d_loss(
            self.discriminator(real_high, real_raw),
            self.discriminator(fake.high.detach(), fake.raw.detach()),
        )
        out = {"d_loss": float(loss.detach())}
        if step % cfg.r1_interval == 0 and cfg.r1_gamma > 0:
            high = real_high.detach().requires_grad_(True)
            raw = real_raw.detach().requires_grad_(True)
            r1 = r1_penalty(self.discriminator(high, raw), [high, raw]).mean()
            loss = loss + r1 * (cfg.r1_gamma / 2) * cfg.r1_interval
            out["r1"] = float(r1.detach())
        opt.opt_d.zero_grad(set_to_none=True)
        loss.backward()
        distributed.average_gradients(self.discriminator.parameters())
        opt.opt_d.step()
        opt.sched_d.step()
        self.discriminator.requires_grad_(False)
        return out
