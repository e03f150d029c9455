"""The :class:`Trainer` of one run: models, optimisers, the run directory (log, checkpoints, samples),
resuming and the training loop. It is made of parts it builds and owns, each given exactly what it
uses: the teacher as the run uses it (:class:`lp3d.training.run_teacher.RunTeacher`), the optimisers
(:class:`lp3d.training.optim.Optimisation`), the per-step work
(:class:`lp3d.training.steps.TrainingSteps`) and the held-out learning curve and sample sheets
(:class:`lp3d.training.heldout.HeldoutViews`); checkpoints are written and read through
:mod:`lp3d.training.checkpoint`'s functions, ``log.csv`` through :mod:`lp3d.training.run_log`.

Imports the modules of :mod:`lp3d.training` before it (``config`` to ``steps``, ``heldout``, ``optim``,
``resume``, ``run_log``), not ``cli``."""

from __future__ import annotations

import json
import os
import signal
import threading
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_write_text
from lp3d.nets.discriminator import DualDiscriminator
from lp3d.teachers import Teacher
from lp3d.training import distributed
from lp3d.training.checkpoint import (
    CHECKPOINT_FORMAT,
    CheckpointError,
    load_shared_checkpoint,
    rank_seed,
    restore_rng_states,
    rng_states,
    write_checkpoint,
)
from lp3d.training.config import TrainConfig
from lp3d.training.heldout import HeldoutViews
from lp3d.training.losses import DistillationLoss
from lp3d.training.optim import Optimisation, student_lr_factor
from lp3d.training.resume import check_resumable
from lp3d.training.run_dir import (
    RunLock,
    checkpoint_path,
    latest_checkpoint,
    remove_stale_temporaries,
    set_aside_checkpoints_after,
)
from lp3d.training.run_log import append_log, start_log
from lp3d.training.run_teacher import RunTeacher
from lp3d.training.steps import Batch, Ranks, TrainingSteps
from lp3d.training.student import SceneBounds, Student, principal_planes
from lp3d.training.synthetic_data import SyntheticDataset
from lp3d.training.teacher_factory import (
    recordable_teacher_args,
    resolve_teacher_args,
    teacher_superres_state,
)
from lp3d.training.tensorboard_log import TensorBoardLog
from lp3d.training.warm_start import warm_start


class Trainer:
    """Owns the models, optimisers, data stream and run directory of one training run.

    Its parts, built here from what each uses: ``run_teacher`` (:class:`RunTeacher`), ``optimisation``
    (:class:`Optimisation`), ``steps`` (:class:`TrainingSteps`, one step of either recipe) and
    ``heldout`` (:class:`HeldoutViews`, the learning curve and sample sheets). The trainer keeps the
    step count and hands it to them.

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
            ``--resume`` and ``lp3d.evaluation.evaluate`` can rebuild it (default: the resumed checkpoint's).
        init_from: a new run's starting weights (:mod:`lp3d.training.warm_start`; ``warm_start.json``).
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
        init_from: str | os.PathLike[str] | None = None,
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

        ckpt = load_shared_checkpoint(resume, self.device) if resume is not None else None
        # Recorded in every checkpoint; a resume without them keeps the recorded ones.
        self.teacher_args = recordable_teacher_args(
            teacher_args if teacher_args is not None else resolve_teacher_args(ckpt)
        )
        if ckpt is not None:
            check_resumable(ckpt, cfg, teacher_name)

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
            self._build(ckpt, init_from)
        except BaseException:
            if self._lock is not None:
                self._lock.release()
            raise

    def _build(self, ckpt: dict[str, Any] | None, init_from: str | os.PathLike[str] | None) -> None:
        """Models, data, optimisers and run directory, continuing ``ckpt`` or starting from ``init_from``."""
        self._build_models()
        self._open_data()
        if ckpt is None:
            self._start_student()
        self.warm_started = None if init_from is None else warm_start(self.student, init_from)
        if self.warm_started is not None:
            distributed.note(self.warm_started.describe())
        self._build_optimisers()
        if ckpt is not None:
            self._restore(ckpt)
            if self.is_main:
                set_aside_checkpoints_after(self.out_dir, self.step)
        else:
            self._start_fresh()
        self.steps.set_trainable(self.step)
        if self.world_size > 1:
            self._note_world()
        if self.is_main:
            self._write_run_dir(fresh=ckpt is None)

    def _build_models(self) -> None:
        """The teacher's side of the run, the student, the discriminator and the held-out views; the
        student's SR starts from the teacher's where it fits."""
        cfg, teacher = self.config, self.teacher
        # Initial weights come from the config's seed (resume overwrites them).
        torch.manual_seed(cfg.seed)
        self.run_teacher = RunTeacher.of(
            teacher,
            self.teacher_name,
            cfg,
            self.device,
            data_cache=self.data_cache,
            progress=self.progress,
        )
        self.student = Student(cfg, teacher.decoder(), self.scene).to(self.device)
        self.discriminator = DualDiscriminator(cfg.discriminator).to(self.device)
        self.heldout = HeldoutViews(self.run_teacher, self.student, self.out_dir)
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

    @property
    def scene(self) -> SceneBounds:
        """The scene bounds of the run's heads (a resumed run's are its checkpoint's)."""
        return self.run_teacher.scene

    @property
    def teacher_decoder(self) -> list[Tensor]:
        """The teacher's decoder weights on the training device."""
        return self.run_teacher.decoder

    def _open_data(self) -> None:
        """The CPU recipe's synthetic dataset and the channel scales of its triplanes (the paper recipe
        synthesises its batches as it goes)."""
        cfg = self.config
        self.dataset: SyntheticDataset | None = None
        self.plane_scale: Tensor | None = None
        if cfg.recipe == "cpu":
            # Under torchrun: rank 0 synthesises a missing dataset, then the other machines' first
            # processes (a no-op on shared storage), then the rest read it.
            self.dataset = distributed.in_turn(self.run_teacher.open_dataset)
            # Channel scales of the normalised L_tri: each channel's spread over identities and texels.
            sample = torch.from_numpy(self.dataset.planes[: min(256, len(self.dataset))].astype(np.float32))
            scale = sample.transpose(0, 2).reshape(sample.shape[2], -1).std(dim=1).clamp_min(1e-3)
            self.plane_scale = scale.to(self.device)

    def _start_student(self) -> None:
        """A new run's student starts from the dataset's principal planes (CPU recipe) or, with
        ``mean_triplane_offset``, from the teacher's mean triplane."""
        cfg = self.config
        if cfg.recipe == "cpu":
            assert self.dataset is not None and self.plane_scale is not None
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
        elif cfg.mean_triplane_offset:
            self.student.start_from_mean(self.run_teacher.mean_planes(cfg.mean_triplane_identities))

    def _build_optimisers(self) -> None:
        """Optimisers, schedules, the AMP scaler, the losses, the data stream and the per-step work,
        at step 0."""
        cfg = self.config
        self.optimisation = Optimisation.build(cfg, self.student, self.discriminator, amp=self.amp)
        self.losses = DistillationLoss(self._perceptual, self._category)
        self.data_rng = np.random.Generator(np.random.PCG64(cfg.seed))
        self.steps = TrainingSteps(
            cfg,
            self.run_teacher,
            self.student,
            self.discriminator,
            self.optimisation,
            self.losses,
            self.data_rng,
            Ranks(self.rank, self.world_size),
            amp=self.amp,
            pretrained_sr=self.pretrained_sr,
            dataset=self.dataset,
            plane_scale=self.plane_scale,
        )
        self.step = 0
        self.interrupted = False

    def _start_fresh(self) -> None:
        """A new run: refuse a run directory that holds checkpoints; under torchrun, every rank takes
        rank 0's starting weights."""
        cfg = self.config
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
            if self.plane_scale is not None:
                distributed.broadcast_tensor(self.plane_scale)
            if not self.is_main:
                torch.manual_seed(rank_seed(cfg.seed, self.rank, 0))

    def _write_run_dir(self, *, fresh: bool) -> None:
        """Rank 0 writes ``config.json``, ``world.json`` and the log's header (keeping a resumed run's
        earlier rows); a new CPU-recipe run logs the untrained student's held-out point."""
        cfg = self.config
        self.out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.out_dir / "config.json", cfg.to_json() + "\n")
        world = {
            "world_size": self.world_size,
            "backend": distributed.backend(),
            "batch_size": cfg.batch_size,
            "batch_per_process": self.local_batch,
        }
        atomic_write_text(self.out_dir / "world.json", json.dumps(world, indent=2) + "\n")
        if fresh and self.warm_started is not None:  # where the weights came from, for the record
            atomic_write_text(self.out_dir / "warm_start.json", self.warm_started.to_json() + "\n")
        start_log(self.out_dir, self.step)
        if cfg.recipe == "cpu" and fresh:
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
        """The student's learning-rate multiplier (:func:`lp3d.training.optim.student_lr_factor`)."""
        return student_lr_factor(self.config, step)

    # -- the parts' work at the current step ---------------------------------------------------------
    def synthesize(self, step: int) -> Batch:
        """The paper recipe's batch of ``step`` (:meth:`TrainingSteps.synthesize`)."""
        return self.steps.synthesize(step)

    def train_step(self, batch: Batch | None = None) -> dict[str, Any]:
        """Run step ``self.step`` (synthesising its batch unless given) and advance; returns the log row."""
        row = self.steps.run(self.step, batch)
        self.step += 1
        return row

    def heldout_metrics(self) -> dict[str, float]:
        """The learning curve's point now (:meth:`HeldoutViews.metrics`)."""
        return self.heldout.metrics()

    def log_heldout(self) -> dict[str, float]:
        """Append the learning curve's point at the current step to ``heldout.csv``."""
        return self.heldout.log(self.step, self._tensorboard())

    def save_samples(
        self, seeds: Sequence[int] | None = None, yaws: Sequence[float] = (-30.0, 0.0, 30.0)
    ) -> Path:
        """``samples/step-NNNNNN.png`` at the current step (:meth:`HeldoutViews.save_samples`)."""
        return self.heldout.save_samples(self.step, self._tensorboard(), seeds, yaws)

    # -- state -------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The checkpoint: tensors, plain numbers and JSON strings only.

        Under torchrun this is a collective call (every rank's RNG states are gathered, so a resume on
        the same number of processes continues each rank's streams): call it on every rank."""
        rngs = distributed.all_gather_objects(rng_states())
        return {
            "format": CHECKPOINT_FORMAT,
            "config": self.config.to_json(),
            "teacher": self.teacher_name,
            "teacher_args": json.dumps(self.teacher_args),
            "scene": json.dumps(asdict(self.scene)),
            "step": self.step,
            "student": self.student.state_dict(),
            "discriminator": self.discriminator.state_dict(),
            **self.optimisation.state_dict(),  # optimizer_g, optimizer_d, scheduler_g, scheduler_d, scaler
            "data_rng": json.dumps(self.data_rng.bit_generator.state),
            "world_size": self.world_size,
            "rng": rngs[0],
            "rng_other_ranks": rngs[1:],
        }

    def _restore(self, ckpt: dict[str, Any]) -> None:
        """Continue from ``ckpt`` (:func:`lp3d.training.checkpoint.load_checkpoint`): every part's
        state is restored in place, the scene bounds and the step are the checkpoint's."""
        try:
            self.student.load_state_dict(ckpt["student"])
            self.discriminator.load_state_dict(ckpt["discriminator"])
            self.optimisation.load_optimisers(ckpt)
        except (RuntimeError, ValueError, KeyError) as e:
            raise CheckpointError(f"checkpoint {ckpt['path']!r} does not fit this run: {e}") from None
        self.optimisation.load_schedules(ckpt)
        self.data_rng.bit_generator.state = json.loads(ckpt["data_rng"])
        recorded = int(ckpt.get("world_size", 1))  # checkpoints from before torchrun: one process
        if recorded != self.world_size:
            distributed.note(
                f"note: checkpoint {ckpt['path']!r} was written by a run of {recorded} process(es), this "
                f"one has {self.world_size}: the data stream, weights and optimiser states carry over, so "
                "it continues the same training up to float rounding (not bit for bit)"
            )
        states = [ckpt["rng"], *ckpt.get("rng_other_ranks", [])]
        restore_rng_states(states[self.rank] if self.rank < len(states) else states[0])
        if self.rank >= len(states):  # a rank the checkpoint has no streams for: its own
            torch.manual_seed(rank_seed(self.config.seed, self.rank, int(ckpt["step"])))
        self.run_teacher.scene = SceneBounds(**json.loads(ckpt["scene"]))
        self.student.scene = self.scene
        self.step = int(ckpt["step"])

    def save_checkpoint(self) -> Path:
        """Write ``checkpoints/step-NNNNNN.pt`` atomically and prune old ones (keeps the last K).
        Under torchrun every rank calls it and rank 0 writes."""
        if self.config.recipe == "cpu" and self.is_main:
            self.log_heldout()  # the other ranks wait in state_dict()'s gather
        state = self.state_dict()  # on every rank: it gathers their RNG states
        if not self.is_main:
            return checkpoint_path(self.out_dir, self.step)
        return write_checkpoint(state, self.out_dir, self.config.keep_checkpoints)

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
                    append_log(self.out_dir, row)
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
