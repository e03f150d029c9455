"""The :class:`Trainer` of one run: models, optimisers, the run directory (log, checkpoints, samples),
resuming, the held-out learning curve and the training loop. Its per-step methods are in
:class:`lp3d.training.steps.TrainingSteps`.

Imports the modules of :mod:`lp3d.training` before it (``config`` to ``steps``), not ``cli``."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import signal
import statistics
import threading
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.nets.discriminator import DualDiscriminator
from lp3d.teachers import Teacher
from lp3d.training import distributed
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.checkpoint import (
    CHECKPOINT_FORMAT,
    CheckpointError,
    _atomic_torch_save,
    _atomic_write_text,
    _load_shared_checkpoint,
    _rank_seed,
    _rng_states,
    _set_rng_states,
)
from lp3d.training.config import TrainConfig, config_differences
from lp3d.training.losses import DistillationLoss
from lp3d.training.run_dir import (
    RunLock,
    checkpoint_path,
    checkpoints,
    latest_checkpoint,
    remove_stale_temporaries,
    set_aside_checkpoints_after,
)
from lp3d.training.steps import TrainingSteps
from lp3d.training.student import SceneBounds, Student, principal_planes, render_teacher, render_views
from lp3d.training.synthetic_data import SyntheticDataset, teacher_fingerprint
from lp3d.training.teacher_factory import _recordable, resolve_teacher_args, teacher_superres_state
from lp3d.training.tensorboard_log import TensorBoardLog

LOG_COLUMNS = [
    "step",
    "stage",
    "reference",
    "seconds",
    "loss",
    "tri",
    *[f"mv_{t}" for t in ("col_raw", "col_high", "perc_raw", "perc_high", "feat", "depth", "adv", "cate")],
    *[f"ref_{t}" for t in ("col_raw", "col_high", "perc_raw", "perc_high", "feat", "depth", "adv", "cate")],
    "sr_col_high",
    "sr_perc_high",
    "ray",
    "d_loss",
    "r1",
    "lr",
]


class Trainer(TrainingSteps):
    """Owns the models, optimisers, data stream and run directory of one training run.

    Args:
        config: the run's configuration (on resume it must equal the checkpoint's).
        out_dir: the run directory (``config.json``, ``log.csv``, ``checkpoints/``, ``samples/``).
        teacher: the frozen teacher; its name is recorded for evaluation.
        teacher_name: ``procedural`` or ``eg3d``.
        perceptual: the perceptual loss module (see :func:`lp3d.training.losses.build_perceptual`).
        device: where to train.
        resume: a checkpoint file or run directory to continue from.
        category: optional category-loss hook (``LossWeights.category`` must be > 0 to use it).
        progress: progress bars (training, dataset synthesis).
        data_cache: where the CPU recipe's synthetic dataset is cached
            (default :func:`lp3d.training.synthetic_data.default_cache_root`).
        teacher_args: how the teacher was built (:data:`TEACHER_ARGS`), recorded in the checkpoints so
            ``--resume`` and ``lp3d.training.eval`` can rebuild it (default: the resumed checkpoint's).
    """

    def __init__(
        self,
        config: TrainConfig,
        out_dir: str | os.PathLike[str],
        *,
        teacher: Teacher,
        teacher_name: str = "procedural",
        perceptual: nn.Module | None = None,
        device: str | torch.device = "cpu",
        resume: str | os.PathLike[str] | None = None,
        category: Any = None,
        progress: bool = True,
        data_cache: str | os.PathLike[str] | None = None,
        teacher_args: dict[str, str | None] | None = None,
    ) -> None:
        self.config = cfg = config
        self.out_dir = Path(out_dir)
        self.device = torch.device(device)
        self.teacher = teacher
        self.teacher_name = teacher_name
        # Under torchrun (lp3d.training.distributed): this process's place, and its share of the global batch.
        self.world_size = distributed.world_size()
        self.rank = distributed.rank()
        self.is_main = self.rank == 0
        if cfg.batch_size % self.world_size != 0:
            raise ValueError(
                f"batch size {cfg.batch_size} is not a multiple of the world size {self.world_size}: "
                "the global batch is split evenly over the processes (change --batch or --nproc-per-node)"
            )
        self.local_batch = cfg.batch_size // self.world_size
        self.progress = progress and self.is_main  # one progress bar, rank 0's
        self.amp = bool(cfg.amp and self.device.type == "cuda")

        ckpt = _load_shared_checkpoint(resume, self.device) if resume is not None else None
        # Recorded in every checkpoint; a resume without them keeps the recorded ones.
        self.teacher_args = _recordable(
            teacher_args if teacher_args is not None else resolve_teacher_args(ckpt)
        )
        if ckpt is not None:
            diff = config_differences(ckpt["train_config"], cfg)
            if diff:
                shown = "\n  ".join(diff[:12]) + ("\n  ..." if len(diff) > 12 else "")
                raise CheckpointError(
                    f"checkpoint {ckpt['path']!r} was trained with configuration "
                    f"{ckpt['train_config'].name!r}, which differs from the requested {cfg.name!r}:\n"
                    f"  {shown}\nresume with the checkpoint's own configuration (omit --config/--batch) "
                    "or start a new run"
                )
            if ckpt["teacher"] != teacher_name:
                raise CheckpointError(
                    f"checkpoint {ckpt['path']!r} was trained with teacher {ckpt['teacher']!r}, "
                    f"not {teacher_name!r}"
                )

        self.data_cache = data_cache
        self._perceptual, self._category = perceptual, category
        self._tb: TensorBoardLog | None = None
        # One trainer per run directory, from before anything in it is written until train() ends;
        # under torchrun rank 0 alone writes it and holds the lock.
        self._lock = RunLock(self.out_dir) if self.is_main else None
        if self._lock is not None:
            self._lock.acquire()
        try:
            if self.is_main:
                remove_stale_temporaries(self.out_dir)
            self._build(ckpt)
        except BaseException:
            if self._lock is not None:
                self._lock.release()
            raise

    def _build(self, ckpt: dict[str, Any] | None) -> None:
        """Models, data, optimisers and run directory (``ckpt``: the checkpoint to continue from)."""
        cfg, teacher = self.config, self.teacher
        # Initial weights come from the config's seed (resume overwrites them).
        torch.manual_seed(cfg.seed)
        probe = teacher.sample(cfg.eval_seed_start)
        self.scene = SceneBounds.of(probe)
        self.student = Student(cfg, teacher.decoder(), self.scene).to(self.device)
        self.discriminator = DualDiscriminator(cfg.discriminator).to(self.device)
        self.teacher_decoder = [torch.as_tensor(a, device=self.device) for a in teacher.decoder()]
        # The paper fine-tunes EG3D's SR; start from the teacher's when it has one that fits.
        self.pretrained_sr = False
        sr_state = teacher_superres_state(teacher)
        if sr_state is not None:
            try:
                self.student.superres.load_state_dict(sr_state, strict=False)
                self.pretrained_sr = True
            except RuntimeError:
                distributed.note(
                    f"note: the teacher's super-resolution does not fit configuration {cfg.name!r}; "
                    "the student's SR starts from scratch and trains from stage 1"
                )

        self.dataset: SyntheticDataset | None = None
        self.heldout: SyntheticDataset | None = None
        self._heldout_truth: list[Tensor] | None = None
        if cfg.recipe == "cpu":
            # Under torchrun: rank 0 synthesises a missing dataset, then the other machines' first
            # processes (a no-op on shared storage), then the rest read it.
            self.dataset = distributed.in_turn(self.open_dataset)
            # Channel scales of the normalised L_tri: each channel's spread over identities and texels.
            sample = torch.from_numpy(self.dataset.planes[: min(256, len(self.dataset))].astype(np.float32))
            self.plane_scale = sample.transpose(0, 2).reshape(sample.shape[2], -1).std(dim=1).clamp_min(1e-3)
            self.plane_scale = self.plane_scale.to(self.device)

        if cfg.recipe == "cpu" and ckpt is None:
            assert self.dataset is not None
            mean, components = principal_planes(
                self.dataset.planes,
                cfg.encoder.basis_components,
                cfg.encoder.basis_resolution,
                self.plane_scale.cpu(),
                mirror=cfg.mirror_augment,
            )
            self.student.start_from_mean(mean.to(self.device))
            if self.student.encoder.basis is not None:
                self.student.encoder.basis.components.data.copy_(components)
        elif cfg.mean_triplane_offset and ckpt is None:
            self.student.start_from_mean(self.mean_teacher_planes(cfg.mean_triplane_identities))

        enc = self.student.encoder
        basis_ids = {id(q) for q in enc.basis.parameters()} if enc.basis is not None else set()
        offset = [] if self.student.plane_offset is None else [self.student.plane_offset]
        betas = tuple(cfg.adam_betas)
        self.opt_g = torch.optim.Adam(
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
                {"params": list(self.student.decoder.parameters()), "lr": cfg.lr_decoder, "name": "decoder"},
                {
                    "params": list(self.student.superres.parameters()),
                    "lr": cfg.lr_superres,
                    "name": "superres",
                },
            ],
            betas=betas,  # type: ignore[arg-type]
        )
        # EG3D's lazy regularisation: R1 every r1_interval steps, with lr and betas adjusted.
        ratio = cfg.r1_interval / (cfg.r1_interval + 1)
        self.opt_d = torch.optim.Adam(
            self.discriminator.parameters(),
            lr=cfg.lr_discriminator * ratio,
            betas=(cfg.discriminator_betas[0] ** ratio, cfg.discriminator_betas[1] ** ratio),
            eps=1e-8,
        )
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, self.lr_factor)
        self.sched_d = torch.optim.lr_scheduler.LambdaLR(self.opt_d, lambda s: 1.0)
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp)
        self.losses = DistillationLoss(self._perceptual, self._category)
        self.data_rng = np.random.Generator(np.random.PCG64(cfg.seed))
        self.step = 0
        self.interrupted = False

        if ckpt is not None:
            self._restore(ckpt)
            if self.is_main:
                set_aside_checkpoints_after(self.out_dir, self.step)
        else:
            if self.is_main and latest_checkpoint(self.out_dir) is not None:
                raise CheckpointError(
                    f"{str(self.out_dir)!r} already holds checkpoints; pass --resume {self.out_dir} to "
                    "continue that run, or choose another --out"
                )
            if self.world_size > 1:
                # Every rank starts from rank 0's weights (built from the same seed, but a start
                # computed from data, e.g. the principal planes, may round differently elsewhere),
                # and the other ranks draw their own dropout masks.
                distributed.broadcast_module(self.student)
                distributed.broadcast_module(self.discriminator)
                if cfg.recipe == "cpu":
                    distributed.broadcast_tensor(self.plane_scale)
                if not self.is_main:
                    torch.manual_seed(_rank_seed(cfg.seed, self.rank, 0))
        self._set_trainable(self.step)
        if self.world_size > 1:
            self._note_world()
        if not self.is_main:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write_text(self.out_dir / "config.json", cfg.to_json() + "\n")
        world = {
            "world_size": self.world_size,
            "backend": distributed.backend(),
            "batch_size": cfg.batch_size,
            "batch_per_process": self.local_batch,
        }
        _atomic_write_text(self.out_dir / "world.json", json.dumps(world, indent=2) + "\n")
        self._init_log()
        if cfg.recipe == "cpu" and ckpt is None:
            self.log_heldout()  # the learning curve starts at the untrained student

    def _note_world(self) -> None:
        """Rank 0 says how the batch is split, and when the discriminator's minibatch-stddev groups
        cannot hold the samples they would hold in one process."""
        cfg, w, per = self.config, self.world_size, self.local_batch
        backend = distributed.backend() or "no process group"
        distributed.note(
            f"world size {w}, batch {cfg.batch_size}, {per} per rank on {w} processes ({backend})"
        )
        group = cfg.discriminator.mbstd_group_size
        if cfg.recipe == "paper" and group > 1 and per % group != 0:
            distributed.note(
                f"note: {per} samples per rank is not a multiple of the discriminator's minibatch-stddev "
                f"group ({group}); each rank forms smaller groups, so the discriminator does not see the "
                f"statistics one process at batch {cfg.batch_size} sees"
            )

    def lr_factor(self, step: int) -> float:
        """The student's learning-rate multiplier: a linear ramp over ``lr_rampup_steps``, then 1 (the
        paper), or with ``lr_cosine_decay`` a cosine to ``lr_final_factor`` at ``total_steps``."""
        cfg = self.config
        ramp = min(1.0, (step + 1) / cfg.lr_rampup_steps) if cfg.lr_rampup_steps > 0 else 1.0
        if not cfg.lr_cosine_decay:
            return ramp
        t = min(1.0, step / cfg.total_steps)
        return ramp * (cfg.lr_final_factor + (1 - cfg.lr_final_factor) * 0.5 * (1 + math.cos(math.pi * t)))

    # -- state -------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The checkpoint: tensors, plain numbers and JSON strings only.

        Under torchrun this is a collective call (every rank's RNG states are gathered, so a resume on
        the same number of processes continues each rank's streams): call it on every rank."""
        rngs = distributed.all_gather_objects(_rng_states())
        return {
            "format": CHECKPOINT_FORMAT,
            "config": self.config.to_json(),
            "teacher": self.teacher_name,
            "teacher_args": json.dumps(self.teacher_args),
            "scene": json.dumps(asdict(self.scene)),
            "step": self.step,
            "student": self.student.state_dict(),
            "discriminator": self.discriminator.state_dict(),
            "optimizer_g": self.opt_g.state_dict(),
            "optimizer_d": self.opt_d.state_dict(),
            "scheduler_g": self.sched_g.state_dict(),
            "scheduler_d": self.sched_d.state_dict(),
            "scaler": self.scaler.state_dict(),
            "data_rng": json.dumps(self.data_rng.bit_generator.state),
            "world_size": self.world_size,
            "rng": rngs[0],
            "rng_other_ranks": rngs[1:],
        }

    def _restore(self, ckpt: dict[str, Any]) -> None:
        try:
            self.student.load_state_dict(ckpt["student"])
            self.discriminator.load_state_dict(ckpt["discriminator"])
            self.opt_g.load_state_dict(ckpt["optimizer_g"])
            self.opt_d.load_state_dict(ckpt["optimizer_d"])
        except (RuntimeError, ValueError, KeyError) as e:
            raise CheckpointError(f"checkpoint {ckpt['path']!r} does not fit this run: {e}") from None
        self.sched_g.load_state_dict(ckpt["scheduler_g"])
        self.sched_d.load_state_dict(ckpt["scheduler_d"])
        if ckpt.get("scaler"):
            self.scaler.load_state_dict(ckpt["scaler"])
        self.data_rng.bit_generator.state = json.loads(ckpt["data_rng"])
        recorded = int(ckpt.get("world_size", 1))  # checkpoints from before torchrun: one process
        if recorded != self.world_size:
            distributed.note(
                f"note: checkpoint {ckpt['path']!r} was written by a run of {recorded} process(es), this "
                f"one has {self.world_size}: the data stream, weights and optimiser states carry over, so "
                "it continues the same training up to float rounding (not bit for bit)"
            )
        states = [ckpt["rng"], *ckpt.get("rng_other_ranks", [])]
        _set_rng_states(states[self.rank] if self.rank < len(states) else states[0])
        if self.rank >= len(states):  # a rank the checkpoint has no streams for: its own
            torch.manual_seed(_rank_seed(self.config.seed, self.rank, int(ckpt["step"])))
        self.scene = SceneBounds(**json.loads(ckpt["scene"]))
        self.student.scene = self.scene
        self.step = int(ckpt["step"])

    def save_checkpoint(self) -> Path:
        """Write ``checkpoints/step-NNNNNN.pt`` atomically and prune old ones (keeps the last K).
        Under torchrun every rank calls it and rank 0 writes."""
        if self.config.recipe == "cpu" and self.is_main:
            self.log_heldout()  # the other ranks wait in state_dict()'s gather
        path = checkpoint_path(self.out_dir, self.step)
        state = self.state_dict()  # on every rank: it gathers their RNG states
        if not self.is_main:
            return path
        _atomic_torch_save(state, path)
        for _, p in checkpoints(self.out_dir)[: -self.config.keep_checkpoints]:
            p.unlink(missing_ok=True)
        return path

    def _set_trainable(self, step: int) -> None:
        """Stage 1 freezes the decoder, and the SR when it came pretrained (supplement, "Training")."""
        if self.config.recipe == "cpu":  # the teacher's decoder is kept; there is no SR to train
            self.student.decoder.requires_grad_(False)
            self.student.superres.requires_grad_(False)
            return
        stage2 = self.config.stage(step) == 2
        self.student.decoder.requires_grad_(stage2)
        self.student.superres.requires_grad_(stage2 or not self.pretrained_sr)

    # -- logging -----------------------------------------------------------------------------------
    def _init_log(self) -> None:
        """Keep the rows of steps before ``self.step`` (a resumed run rewrites what came after)."""
        path = self.out_dir / "log.csv"
        rows: list[dict[str, str]] = []
        if path.exists() and self.step > 0:
            with open(path, newline="") as f:
                rows = [
                    r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) < self.step
                ]
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, LOG_COLUMNS)
            w.writeheader()
            w.writerows(rows)

    def _log(self, row: dict[str, Any]) -> None:
        with open(self.out_dir / "log.csv", "a", newline="") as f:
            csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore").writerow(
                {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()}
            )

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

    # -- the loop ----------------------------------------------------------------------------------
    def train(self, max_steps: int | None = None) -> dict[str, Any] | None:
        """Train until global step ``max_steps`` (default: the config's total), with checkpoints every
        ``checkpoint_every`` steps and at the end. Returns the last log row.

        Ctrl-C (in the main thread) finishes the current step, saves a checkpoint and returns with
        ``self.interrupted`` set; a second Ctrl-C aborts at once (the last checkpoint stays valid).
        """
        if self._lock is not None:
            self._lock.acquire()  # released below: the run directory is free once train() returns
        try:
            if self.is_main:
                self._tensorboard()  # opened at the start step, so a resume purges what came after it
            row = self._train(max_steps)
            distributed.barrier()  # under torchrun: every rank returns once rank 0 has written the end
            return row
        finally:
            self.close()

    def close(self) -> None:
        """Flush the event files and give up the run directory (train() does this when it returns)."""
        if self._tb is not None:
            self._tb.close()
            self._tb = None
        if self._lock is not None:
            self._lock.release()

    def _tensorboard(self) -> TensorBoardLog:
        """The run's TensorBoard writer (a no-op without the package), opened at first use."""
        if self._tb is None:
            self._tb = TensorBoardLog(self.out_dir, start_step=self.step)
        return self._tb

    def _train(self, max_steps: int | None) -> dict[str, Any] | None:
        cfg = self.config
        end = cfg.total_steps if max_steps is None else max_steps
        self.interrupted = False
        if self.step >= end:
            distributed.note(f"already at step {self.step} >= {end}; nothing to do")
            return None
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(
                total=end, initial=self.step, desc=f"train {cfg.name}", unit="step", dynamic_ncols=True
            )

        def on_sigint(signum: int, frame: Any) -> None:
            if self.interrupted:
                raise KeyboardInterrupt
            self.interrupted = True
            distributed.note("\nstopping after this step (Ctrl-C again to abort)")

        previous = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGINT, on_sigint)
        row: dict[str, Any] | None = None
        try:
            while self.step < end and not self.interrupted:
                row = self.train_step()
                if self.is_main:
                    self._log(row)
                    self._tensorboard().step_row(row)
                if bar is not None:
                    bar.update(1)
                    post = {"stage": row["stage"], "loss": f"{row['loss']:.4f}"}
                    for key in ("tri", "ray", "mv_col_high", "ref_col_high", "d_loss"):
                        if key in row:
                            post[key] = f"{row[key]:.4f}"
                    bar.set_postfix(post, refresh=False)
                if cfg.sample_every and self.step % cfg.sample_every == 0 and self.is_main:
                    self.save_samples()  # the other ranks wait at their next collective call
                if self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
                # Under torchrun a Ctrl-C reaches the ranks at different moments: all stop together.
                self.interrupted = distributed.any_rank(self.interrupted, self.device)
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)
            if bar is not None:
                bar.close()
        if self.step % cfg.checkpoint_every != 0:
            self.save_checkpoint()
        if cfg.sample_every and self.step % cfg.sample_every != 0 and not self.interrupted and self.is_main:
            self.save_samples()
        return row
