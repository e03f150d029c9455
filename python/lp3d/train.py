"""Distil a teacher into the LP3D encoder with synthetic data (paper §3.2, supplement "Training").

``python -m lp3d.train --config tiny --out runs/t`` trains the ``tiny`` configuration on the embedded
procedural teacher; ``--resume runs/t`` continues it exactly where it stopped.

One step (supplement, "Training"):

1. **Synthesis.** B identities (fresh seeds from the training range; evaluation seeds are disjoint),
   one reference camera ``P_ref`` (augmented, :data:`lp3d.camera_sampling.FFHQ_REFERENCE`) and one
   multiview camera ``P_mv`` (:data:`~lp3d.camera_sampling.FFHQ_MULTIVIEW`) each. The frozen teacher
   renders, with the torch twin of the renderer: the encoder's input I_ref at the encoder's image size,
   and for each view set the targets I_f, I_raw (= I_f[:3]) and I_D at the raw resolution and I_high
   at the image size.
2. **Student.** T̄ = E(I_ref); T̄ is rendered from P_mv (and from P_ref on reference steps) with the
   student's decoder, then super-resolved.
3. **Loss** (Eq. 5, :mod:`lp3d.losses`) and one optimiser step; in stage 2 also a discriminator step
   on teacher (real) vs student (fake) renders, with lazy R1.

Two-stage schedule (supplement): stage 1 (``warmup_steps``) without adversarial and category losses,
the reference-view loss every 10th synthesis, decoder and super-resolution frozen; stage 2 all losses
and all parameters, triplane weight 0.01, no feature loss, reference loss every 2nd step and, from
``dense_reference_from``, every step. Step counts are scaled per configuration (paper: 30k, 37.5k and
220k of batch 32 on 8 A100s).

Decisions where the paper is silent or the setting differs (all visible in :class:`TrainConfig`):

* **Teacher high-resolution images.** EG3D's I_512 comes out of its super-resolution network. A
  teacher may offer the same through the optional method ``superresolve(features (B,32,r,r)) ->
  (B,3,R,R)`` (the EG3D adapter's, with the constant w) and pretrained student SR weights through
  ``generator.superresolution`` (EG3D) or ``superres_state_dict()``. The procedural
  teacher has neither: its I_high (and the encoder input) are direct volume renders at the encoder's
  image size, which is exact and affordable on a CPU for the small configurations (a 128² render of
  12+12 samples per ray). In stage 1 the SR's parameters never learn from the student's loss (the
  paper freezes its pretrained SR; the student's high-resolution terms still reach the triplane through
  it). With no pretrained SR (procedural teacher), stage 1 trains it on the teacher's own pairs
  I_f -> I_high (L1 + perceptual at high resolution, logged as ``sr_*``), as EG3D's SR learnt from its
  generator's renders. The student decoder starts as a copy of the teacher's (the paper fine-tunes
  EG3D's) and is frozen in stage 1.
* **Alternating supervision.** "We compute losses for the reference set of cameras once every 10
  triplane syntheses": on those steps the reference-view terms are added to the multiview terms of the
  same step (one backward pass), rather than taking a separate gradient step.
* **Optimisers.** Adam with the paper's learning rates (1e-4; transformer 5e-5); betas (0.9, 0.999)
  (not stated); the decoder and the SR have their own rates (not stated; 1e-4 by default). The CPU
  configurations train their SR from scratch at 1e-3 and fine-tune the procedural decoder at 1e-6:
  its hand-built hidden units reach hundreds (gate slopes of 600-1500), so an Adam step of size lr on
  every weight moves its colour outputs by ~300·lr, and 1e-3 visibly broke the colours the moment
  stage 2 unfroze it. The discriminator uses
  EG3D's settings: Adam lr 0.002, betas (0, 0.99), R1 gamma 1 every 16 steps (lazy regularisation).
* **Depth.** I_D is rendered and logged; Eq. 5 has no depth term, so its weight is 0 by default.
* **Mean-triplane start** (CPU configurations only, ``mean_triplane_offset``): the student predicts
  an offset from the mean teacher triplane, as pSp/e4e predict offsets from the mean latent. Learning
  the head layout shared by every identity from scratch costs the tiny encoder more steps than a CPU
  test can afford; the paper's configurations train from scratch as published.
* **AMP** (CUDA only): the encoder's forward runs under fp16 autocast (the supplement's inference
  setting) with a gradient scaler; rendering, SR and the discriminator stay in float32.

The CPU recipe (``recipe="cpu"``: ``small``, ``tiny``; ``full``/``lt`` keep the published recipe).
The paper's step costs about 20 s on a 2-core CPU at batch 4 (``bench/train_profile.py``), most of it
synthesising and rendering the teacher and rendering whole student images, and its loss reaches the
encoder mainly through renders of a step-like procedural decoder. The CPU recipe spends the CPU on
the encoder instead:

* **Data made once.** ``dataset_identities`` teacher identities (planes at the student's resolution
  and one input render each) are synthesised once into a content-hashed cache
  (:mod:`lp3d.synthetic_data`) and reused across steps, runs and resumes; horizontal flips with
  mirrored planes (:func:`lp3d.triplane.mirror_planes`) double them.
* **Triplane regression.** For ``regression_steps`` the only loss is L_tri with every channel
  divided by its spread over identities (:func:`lp3d.losses.normalised_triplane_loss`); after them an
  RGB L1 on ``rays_per_identity`` random rays of a random multiview camera is added (teacher and
  student rendered on the same rays; :func:`lp3d.render_torch.render_rays`). ``small`` and ``tiny``
  regress for their whole schedule: with the procedural teacher's step-like decoder the ray loss
  made things worse (the shipped run, steps 500-600 with rays: held-out PSNR 18.4 -> 18.1 dB and
  identity specificity 3.8 -> 3.2 dB, L_tri 0.125 -> 0.143; ``python/lp3d/models/README.md``).
* **A plane basis.** The teacher's triplanes span its identities in about a hundred dimensions (the
  principal components of 512 heads and their mirrors leave 3 % of the held-out L1 at 128
  components), so the CPU encoders carry :class:`lp3d.encoder.PlaneBasis`, started from those
  components (:func:`principal_planes`), beside the convolutional head; the student starts at the
  dataset's mean triplane.
* **No SR and no discriminator.** The procedural teacher renders its high-resolution image directly,
  and so does the student (``Student.render``); the decoder is the teacher's, frozen.
* **A cosine learning-rate decay** to 5 % at ``total_steps``, and a learning curve on held-out
  identities (``heldout.csv``: PSNR against their own and against other identities' teachers, and
  the identity specificity) at every checkpoint.

Checkpoints are plain dicts of tensors and JSON strings (``torch.load(weights_only=True)``), written
atomically; they carry the optimiser, scheduler, scaler and every RNG state, so resuming is exact.

**Distributed training** (``torchrun --nproc-per-node N -m lp3d.train ...``; :mod:`lp3d.distributed`,
``docs/training.md``). Each process takes ``cuda:LOCAL_RANK`` (NCCL) or the CPU (gloo) and builds its
own teacher and models from the same seed (rank 0's weights are broadcast). ``batch_size`` is the
global batch and must be a multiple of N: every rank draws the whole step's randomness from the one
seeded data stream and keeps the rows ``rank, rank + N, ...`` (the CPU recipe's dataset rows, flips
and rays likewise), so the stream does not depend on N. After each backward pass the student's and
the discriminator's gradients are averaged over the ranks by hand (no ``DistributedDataParallel``:
the student is called through ``encode``/``render``, parts freeze between stages and R1 takes a double
backward); ``log.csv`` holds the losses' means over the ranks. Rank 0 alone holds ``.lock`` and
writes the run directory (``world.json`` records N), computes the held-out curve and the samples
while the others wait, and synthesises a missing dataset before the others read it. Checkpoints
record N and every rank's RNG states: a resume on N processes is exact; on another number it is
allowed, with a note, and continues the same training up to float rounding. Without torchrun nothing
of this runs and one process trains exactly as described above.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import random
import signal
import statistics
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d import distributed
from lp3d.atomic import atomic_path
from lp3d.camera_sampling import FFHQ_MULTIVIEW, FFHQ_REFERENCE, CameraDistribution, sample_cameras
from lp3d.discriminator import (
    DISCRIMINATOR_CONFIGS,
    DiscriminatorConfig,
    DualDiscriminator,
    d_loss,
    r1_penalty,
)
from lp3d.encoder import CONFIGS as ENCODER_CONFIGS
from lp3d.encoder import EncoderConfig, LP3DEncoder
from lp3d.errors import EXIT_ERROR, EXIT_INTERRUPTED, run_command
from lp3d.losses import (
    PERCEPTUAL_KINDS,
    DistillationLoss,
    LossWeights,
    ViewRenders,
    build_perceptual,
    l1,
    normalised_triplane_loss,
)
from lp3d.render_torch import rays_from_cameras, render_rays, render_torch
from lp3d.run_dir import (
    RunLock,
    checkpoint_path,
    checkpoints,
    latest_checkpoint,
    newest_readable,
    remove_stale_temporaries,
    set_aside_checkpoints_after,
)
from lp3d.superres import SUPERRES_CONFIGS, SuperresConfig, SuperResolution
from lp3d.synthetic_data import DatasetKey, SyntheticDataset, resize_planes, teacher_fingerprint
from lp3d.teachers import Teacher
from lp3d.tensorboard_log import TensorBoardLog
from lp3d.triplane import TriplaneData, mirror_planes

__all__ = [
    "CHECKPOINT_FORMAT",
    "TEACHERS",
    "TRAIN_CONFIGS",
    "CheckpointError",
    "NonFiniteError",
    "SceneBounds",
    "Student",
    "TrainConfig",
    "Trainer",
    "build_teacher",
    "load_checkpoint",
    "render_teacher",
    "render_views",
    "teacher_superres_state",
    "main",
]

#: Identifies lp3d training checkpoints; bumped when the layout changes.
CHECKPOINT_FORMAT = "lp3d-train-checkpoint-v1"
TEACHERS = ("procedural", "eg3d")
RECIPES = ("paper", "cpu")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used here (another configuration, another format, a bad file)."""


class NonFiniteError(ValueError):
    """NaN/Inf in a training batch or loss; the message names the step, the tensor and the seeds."""


# --------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------


#: Stage-1 weights: Eq. 5 without the adversarial and category losses (supplement, "Training").
WARMUP_WEIGHTS = LossWeights(adversarial_reference=0.0, adversarial_multiview=0.0, category=0.0)
#: Stage-2 weights: all losses, triplane weight 0.01, feature loss removed (supplement, "Training").
MAIN_WEIGHTS = LossWeights(triplane=0.01, feature=0.0)


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run; saved as ``config.json`` in the run directory.

    Resolutions: the encoder reads ``encoder.image_size``² images and writes
    ``encoder.triplane_resolution``² planes; the renderer draws ``raw_resolution``² feature images
    (the SR's input) that the SR lifts to ``superres.output_resolution`` = ``encoder.image_size``
    (I_high), which the dual discriminator judges.
    """

    name: str
    encoder: EncoderConfig
    superres: SuperresConfig
    discriminator: DiscriminatorConfig
    raw_resolution: int
    #: Coarse and importance samples per ray (paper: 48 + 48 for training).
    depth_resolution: int = 48
    depth_resolution_importance: int = 48
    reference_cameras: CameraDistribution = FFHQ_REFERENCE
    multiview_cameras: CameraDistribution = FFHQ_MULTIVIEW
    batch_size: int = 32
    #: The two-stage schedule (supplement): stage 1 is [0, warmup_steps); stage 2 computes the
    #: reference loss every ``reference_every_main`` steps until ``dense_reference_from``, then always.
    total_steps: int = 220_000
    warmup_steps: int = 30_000
    dense_reference_from: int = 37_500
    reference_every_warmup: int = 10
    reference_every_main: int = 2
    lr_encoder: float = 1e-4
    lr_transformer: float = 5e-5
    #: The plane basis's coefficient MLP and components (CPU configurations' encoders only).
    lr_basis: float = 1e-4
    #: Decoder and super-resolution (fine-tuned in stage 2; not given in the paper).
    lr_decoder: float = 1e-4
    lr_superres: float = 1e-4
    adam_betas: tuple[float, float] = (0.9, 0.999)
    #: Linear learning-rate ramp over the first steps (0: constant, as in the paper).
    lr_rampup_steps: int = 0
    #: Cosine decay of the student's learning rates to ``lr_final_factor`` at ``total_steps`` (the
    #: CPU recipe; the paper keeps them constant).
    lr_cosine_decay: bool = False
    lr_final_factor: float = 0.05
    #: Global gradient-norm clip for the student (0: off).
    grad_clip: float = 0.0
    lr_discriminator: float = 0.002
    discriminator_betas: tuple[float, float] = (0.0, 0.99)
    r1_gamma: float = 1.0
    r1_interval: int = 16
    warmup_weights: LossWeights = WARMUP_WEIGHTS
    main_weights: LossWeights = MAIN_WEIGHTS
    #: ``lpips`` (needs backbone weights on disk), ``ssim-grad`` (weight-free) or ``none``.
    perceptual: str = "lpips"
    lpips_net: str = "vgg"
    #: Identities are drawn from [train_seeds[0], train_seeds[1]); evaluation uses seeds from
    #: ``eval_seed_start`` on, so held-out identities are never trained on.
    train_seeds: tuple[int, int] = (0, 1_000_000)
    eval_seed_start: int = 1_000_000
    #: Predict the triplane as an offset from the mean teacher triplane (of ``mean_triplane_identities``
    #: training identities), as pSp/e4e predict offsets from the mean latent w_avg: a learned
    #: (3, 32, T, T) offset initialised to that mean, plus the encoder with its last convolution
    #: zeroed. Not in the paper (off for full/lt); on for the CPU configurations, whose few hundred
    #: steps are otherwise spent learning the shared head layout from scratch.
    mean_triplane_offset: bool = False
    mean_triplane_identities: int = 32
    #: ``paper``: the two-stage recipe above (full, lt). ``cpu``: the CPU distillation recipe
    #: (small, tiny; see "The CPU recipe" in the module docstring): a cached synthetic dataset of
    #: ``dataset_identities`` identities, channel-normalised triplane regression for
    #: ``regression_steps`` steps, then that plus an RGB L1 on ``rays_per_identity`` random rays of a
    #: random multiview camera, teacher and student rendered from their planes; no super-resolution
    #: (the student's final image is a direct volume render at ``image_size``, as the procedural
    #: teacher's is) and no discriminator.
    recipe: str = "paper"
    dataset_identities: int = 4096
    regression_steps: int = 0
    rays_per_identity: int = 0
    triplane_weight: float = 1.0
    ray_weight: float = 1.0
    #: CPU recipe: flip half the inputs horizontally and mirror their target planes to match.
    mirror_augment: bool = False
    #: CPU recipe: held-out identities of the learning curve (``heldout.csv``, at every checkpoint).
    heldout_identities: int = 16
    #: Seeds the initial weights and the data stream.
    seed: int = 0
    #: Preview PNG every this many steps and at the end (0: never).
    sample_every: int = 1000
    checkpoint_every: int = 5000
    keep_checkpoints: int = 3
    #: fp16 autocast for the encoder forward, on CUDA only.
    amp: bool = True

    def __post_init__(self) -> None:
        self.validate()

    @property
    def image_size(self) -> int:
        return self.encoder.image_size

    @property
    def triplane_resolution(self) -> int:
        return self.encoder.triplane_resolution

    def stage(self, step: int) -> int:
        """1 (warm-up) or 2 for the 0-based ``step``."""
        return 1 if step < self.warmup_steps else 2

    def reference_step(self, step: int) -> bool:
        """Whether ``step`` computes the reference-view loss (supplement, "Training")."""
        if step < self.warmup_steps:
            return step % self.reference_every_warmup == 0
        if step < self.dense_reference_from:
            return (step - self.warmup_steps) % self.reference_every_main == 0
        return True

    def weights(self, step: int) -> LossWeights:
        return self.warmup_weights if self.stage(step) == 1 else self.main_weights

    def validate(self) -> None:
        """Raise ValueError naming the inconsistent fields."""
        ints = ("raw_resolution", "depth_resolution", "batch_size", "total_steps", "reference_every_warmup")
        for name in (
            *ints,
            "reference_every_main",
            "r1_interval",
            "checkpoint_every",
            "mean_triplane_identities",
            "dataset_identities",
            "heldout_identities",
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"TrainConfig.{name} must be a positive int, got {v!r}")
        for name in (
            "depth_resolution_importance",
            "warmup_steps",
            "dense_reference_from",
            "lr_rampup_steps",
            "regression_steps",
            "rays_per_identity",
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"TrainConfig.{name} must be an int >= 0, got {v!r}")
        if not self.warmup_steps <= self.dense_reference_from:
            raise ValueError("TrainConfig: warmup_steps must be <= dense_reference_from")
        if self.raw_resolution != self.superres.input_resolution:
            raise ValueError(
                f"TrainConfig.raw_resolution ({self.raw_resolution}) must equal the SR's input_resolution "
                f"({self.superres.input_resolution})"
            )
        if self.superres.output_resolution != self.encoder.image_size:
            raise ValueError(
                f"TrainConfig: the SR output ({self.superres.output_resolution}) must equal the encoder's "
                f"image_size ({self.encoder.image_size}): I_high is both a target and the encoder input"
            )
        if self.discriminator.resolution != self.encoder.image_size:
            raise ValueError(
                f"TrainConfig: the discriminator resolution ({self.discriminator.resolution}) must equal "
                f"the encoder's image_size ({self.encoder.image_size})"
            )
        if self.superres.in_channels != self.encoder.plane_channels:
            raise ValueError("TrainConfig: the SR's in_channels must equal the encoder's plane_channels")
        lo, hi = self.train_seeds
        if not (0 <= lo < hi <= self.eval_seed_start):
            raise ValueError(
                f"TrainConfig: train_seeds {self.train_seeds} must be a non-empty range below "
                f"eval_seed_start ({self.eval_seed_start}) so held-out identities are never trained on"
            )
        if self.perceptual not in PERCEPTUAL_KINDS:
            raise ValueError(f"TrainConfig.perceptual must be one of {list(PERCEPTUAL_KINDS)}")
        if self.lpips_net not in ("vgg", "alex"):
            raise ValueError(f"TrainConfig.lpips_net must be 'vgg' or 'alex', got {self.lpips_net!r}")
        for name in (
            "lr_encoder",
            "lr_transformer",
            "lr_basis",
            "lr_decoder",
            "lr_superres",
            "lr_discriminator",
            "r1_gamma",
            "triplane_weight",
            "ray_weight",
            "lr_final_factor",
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"TrainConfig.{name} must be a finite number >= 0, got {v!r}")
        if self.keep_checkpoints < 1:
            raise ValueError("TrainConfig.keep_checkpoints must be >= 1")
        if self.recipe not in RECIPES:
            raise ValueError(f"TrainConfig.recipe must be one of {list(RECIPES)}, got {self.recipe!r}")
        if self.recipe == "cpu" and self.dataset_identities > self.train_seeds[1] - self.train_seeds[0]:
            raise ValueError("TrainConfig.dataset_identities exceeds the training seed range")

    # -- JSON --------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if hasattr(v, "to_dict"):
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"TrainConfig.from_dict: unknown keys {unknown}")
        nested = {
            "encoder": EncoderConfig,
            "superres": SuperresConfig,
            "discriminator": DiscriminatorConfig,
            "reference_cameras": CameraDistribution,
            "multiview_cameras": CameraDistribution,
            "warmup_weights": LossWeights,
            "main_weights": LossWeights,
        }
        kwargs: dict[str, Any] = {}
        for k, v in data.items():
            if k in nested:
                kwargs[k] = nested[k].from_dict(v)
            elif isinstance(v, list):
                kwargs[k] = tuple(v)
            else:
                kwargs[k] = v
        return cls(**kwargs)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> TrainConfig:
        return cls.from_dict(json.loads(text))


def _scaled_schedule(total: int, base: TrainConfig | None = None) -> dict[str, int]:
    """The paper's stage boundaries (30k and 37.5k of 220k) scaled to ``total`` steps; with ``base``,
    the CPU recipe's regression phase keeps its share of ``base``'s schedule too (a config that
    regresses for its whole schedule still does)."""
    out = {
        "total_steps": total,
        "warmup_steps": round(total * 30_000 / 220_000),
        "dense_reference_from": round(total * 37_500 / 220_000),
    }
    if base is not None:
        out["regression_steps"] = round(total * base.regression_steps / base.total_steps)
    return out


def _cpu_config(
    name: str, *, samples: int, batch_size: int, total_steps: int, lr_rampup_steps: int, sizes: str = ""
) -> TrainConfig:
    """The paper's two-stage recipe scaled to a CPU, with the network sizes ``sizes`` (default
    ``name``: ``small`` or ``tiny``); see :data:`TRAIN_CONFIGS`."""
    sizes = sizes or name
    return TrainConfig(
        name=name,
        encoder=ENCODER_CONFIGS[name if name in ENCODER_CONFIGS else sizes],
        superres=SUPERRES_CONFIGS[sizes],
        discriminator=DISCRIMINATOR_CONFIGS[sizes],
        raw_resolution=64,
        depth_resolution=samples,
        depth_resolution_importance=samples,
        batch_size=batch_size,
        **_scaled_schedule(total_steps),
        lr_decoder=1e-6,
        lr_superres=1e-3,
        lr_rampup_steps=lr_rampup_steps,
        grad_clip=10.0,
        perceptual="ssim-grad",
        mean_triplane_offset=True,
        sample_every=50,
        checkpoint_every=50,
    )


def _cpu_recipe_config(
    name: str,
    *,
    samples: int,
    batch_size: int,
    total_steps: int,
    regression_steps: int,
    dataset_identities: int,
) -> TrainConfig:
    """The CPU recipe (``recipe="cpu"``, see :class:`TrainConfig`) at the ``name`` network sizes."""
    return dataclasses.replace(
        _cpu_config(
            name, samples=samples, batch_size=batch_size, total_steps=total_steps, lr_rampup_steps=50
        ),
        recipe="cpu",
        lr_encoder=3e-4,
        lr_transformer=1.5e-4,
        lr_basis=1e-3,
        lr_decoder=0.0,
        dataset_identities=dataset_identities,
        regression_steps=regression_steps,
        rays_per_identity=512,
        mirror_augment=True,
        lr_cosine_decay=True,
        sample_every=250,
        checkpoint_every=100,
        keep_checkpoints=30,
    )


#: Named configurations. ``full`` and ``lt`` are the paper's (87M / 63M encoders, EG3D's 128 -> 512
#: SR and discriminator, 48 + 48 samples, batch 32, 220k steps). ``small`` and ``tiny`` fit a CPU:
#: smaller encoders and SR, 64² raw renders, few samples per ray, small batches, short schedules with
#: the same stage proportions, the paper's encoder learning rates but 1e-3 for the SR (learnt from
#: scratch), a start from the mean teacher triplane (``mean_triplane_offset``), and the weight-free
#: ``ssim-grad`` perceptual loss as their stated default (LPIPS backbones are not available on a fresh
#: machine; ``--perceptual lpips`` selects LPIPS).
TRAIN_CONFIGS: dict[str, TrainConfig] = {
    "full": TrainConfig(
        name="full",
        encoder=ENCODER_CONFIGS["full"],
        superres=SUPERRES_CONFIGS["eg3d"],
        discriminator=DISCRIMINATOR_CONFIGS["eg3d"],
        raw_resolution=128,
    ),
    "lt": TrainConfig(
        name="lt",
        encoder=ENCODER_CONFIGS["lt"],
        superres=SUPERRES_CONFIGS["eg3d"],
        discriminator=DISCRIMINATOR_CONFIGS["eg3d"],
        raw_resolution=128,
    ),
    "small": _cpu_recipe_config(
        "small", samples=16, batch_size=8, total_steps=4_000, regression_steps=4_000, dataset_identities=2048
    ),
    "tiny": _cpu_recipe_config(
        "tiny", samples=12, batch_size=4, total_steps=1_000, regression_steps=1_000, dataset_identities=512
    ),
    # The paper's two-stage recipe with the first CPU encoder: what shipped before the CPU recipe,
    # kept as the reference row of bench/train_profile.py.
    "small-paper": _cpu_config(
        "small-paper", sizes="small", samples=16, batch_size=4, total_steps=2_000, lr_rampup_steps=20
    ),
    # The paper's two-stage recipe at the tiny size: what the tests run of the full/lt machinery
    # (reference schedule, SR from teacher pairs, discriminator, R1) on a CPU.
    "tiny-paper": _cpu_config(
        "tiny-paper", sizes="tiny", samples=12, batch_size=2, total_steps=1_000, lr_rampup_steps=10
    ),
}


# --------------------------------------------------------------------------------------------------
# Teacher
# --------------------------------------------------------------------------------------------------


def build_teacher(
    name: str,
    *,
    triplane_resolution: int,
    teacher_pkl: str | None = None,
    eg3d_source: str | None = None,
    conditioning: str = "gen_videos",
    device: str | torch.device = "cpu",
) -> Teacher:
    """The teacher ``name``: ``procedural`` (built at the encoder's triplane resolution, so L_tri needs
    no resampling) or ``eg3d`` (``lp3d.teachers.eg3d.EG3DTeacher.from_pickle``, imported only when asked
    for: loading a pickle executes its code; ``conditioning``: whose conditioning camera, see there)."""
    if name == "procedural":
        from lp3d.teachers import ProceduralTeacher

        return ProceduralTeacher(resolution=triplane_resolution)
    if name == "eg3d":
        try:
            from lp3d.teachers import eg3d  # type: ignore[attr-defined]
        except ImportError as e:
            raise RuntimeError(
                "the EG3D teacher adapter (lp3d.teachers.eg3d) is not available in this installation "
                f"({e}); train with --teacher procedural"
            ) from None
        if teacher_pkl is None:
            raise ValueError(
                "--teacher eg3d needs --teacher-pkl PATH (an official EG3D generator pickle, e.g. "
                "ffhqrebalanced512-128.pkl) and usually --eg3d-source DIR (NVlabs/eg3d's eg3d/ folder)"
            )
        return eg3d.EG3DTeacher.from_pickle(
            teacher_pkl,
            eg3d_source=eg3d_source,
            device=device,
            conditioning=conditioning,  # type: ignore[arg-type]
        )
    raise ValueError(f"unknown teacher {name!r}; choose one of {list(TEACHERS)}")


#: The arguments of :func:`build_teacher` besides the name that a run records in its checkpoints, so
#: that ``--resume`` and ``lp3d.eval`` rebuild the same teacher without being told again.
TEACHER_ARGS = ("teacher_pkl", "eg3d_source", "conditioning")


def resolve_teacher_args(ckpt: dict[str, Any] | None, **given: str | None) -> dict[str, str | None]:
    """The teacher arguments to use: those ``given`` (command-line overrides) where not None, else those
    recorded in ``ckpt`` (paths as absolute as they were recorded), else the defaults."""
    recorded = json.loads(ckpt.get("teacher_args", "{}")) if ckpt is not None else {}
    out: dict[str, str | None] = {"teacher_pkl": None, "eg3d_source": None, "conditioning": "gen_videos"}
    for k in TEACHER_ARGS:
        if given.get(k) is not None:
            out[k] = given[k]
        elif recorded.get(k) is not None:
            out[k] = recorded[k]
    return out


def _recordable(args: dict[str, str | None]) -> dict[str, str | None]:
    """``args`` with paths made absolute, so a resume from another directory finds them."""
    return {
        k: (str(Path(v).expanduser().resolve()) if k != "conditioning" and v else v) for k, v in args.items()
    }


def teacher_superres_state(teacher: Teacher) -> dict[str, Tensor] | None:
    """Pretrained SR weights a teacher offers for the student (EG3D's ``G.superresolution``), or None."""
    fn = getattr(teacher, "superres_state_dict", None)
    if callable(fn):
        return fn()
    module = getattr(getattr(teacher, "generator", None), "superresolution", None)
    if isinstance(module, nn.Module):
        return module.state_dict()
    return None


@dataclass(frozen=True)
class SceneBounds:
    """The teacher's box and ray range, shared by all its triplanes (and the student's)."""

    box_warp: float
    ray_start: float
    ray_end: float

    @classmethod
    def of(cls, tri: TriplaneData) -> SceneBounds:
        return cls(float(tri.box_warp), float(tri.ray_start), float(tri.ray_end))


def dataset_key(cfg: TrainConfig, teacher: Teacher, teacher_name: str) -> DatasetKey:
    """The cache key of the CPU recipe's synthetic dataset for a configuration and teacher."""
    return DatasetKey(
        teacher=teacher_name,
        teacher_fingerprint=teacher_fingerprint(teacher, cfg.train_seeds[0]),
        first_seed=cfg.train_seeds[0],
        n_identities=cfg.dataset_identities,
        image_size=cfg.image_size,
        triplane_resolution=cfg.triplane_resolution,
        depth_resolution=cfg.depth_resolution,
        depth_resolution_importance=cfg.depth_resolution_importance,
        reference_cameras=cfg.reference_cameras.to_dict(),
        camera_seed=cfg.seed,
    )


@torch.no_grad()
def principal_planes(
    planes: np.ndarray, k: int, resolution: int, scale: Tensor, *, mirror: bool = False, limit: int = 2048
) -> tuple[Tensor, Tensor]:
    """The mean (3, C, T, T) of teacher triplanes (N, 3, C, T, T) and their first ``k`` principal
    components at ``resolution``², as (k, 3·C, r, r) scaled so unit coefficients are one standard
    deviation (the plane basis's start, :class:`lp3d.encoder.PlaneBasis`).

    Channels are divided by ``scale`` (C,) before the analysis, as in the normalised L_tri, so the
    components favour what that loss weighs. ``mirror`` adds the mirrored planes (the training
    augmentation). At most ``limit`` planes are used (the Gram matrix is limit²)."""
    x = torch.from_numpy(np.asarray(planes[: limit // 2 if mirror else limit], dtype=np.float32))
    if mirror:
        x = torch.cat([x, mirror_planes(x)])
    n, p, c, t, _ = x.shape
    mean = x.mean(0)
    if k == 0:
        return mean, torch.zeros(0, p * c, resolution, resolution)
    if n < 2:
        raise ValueError(f"principal planes need at least 2 planes, got {n}")
    found = min(k, n - 1)  # a small dataset (tests, trials) has n - 1 directions; the rest start at zero
    if found < k:
        distributed.note(f"note: {n} planes give {found} principal planes; {k - found} start at zero")
    small = x.reshape(n, p * c, t, t)
    if resolution != t:
        small = F.interpolate(small, size=(resolution, resolution), mode="bilinear", antialias=True)
    per_channel = scale.repeat(p).reshape(1, p * c, 1, 1)
    z = ((small - small.mean(0, keepdim=True)) / per_channel).reshape(n, -1).double()
    eigval, eigvec = torch.linalg.eigh(z @ z.T)  # ascending; Gram trick: n << dimensions
    eigval, eigvec = eigval.flip(0)[:found].clamp_min(1e-12), eigvec.flip(1)[:, :found]
    # Unit-norm directions u = zᵀv/√λ; one standard deviation along them is √(λ/n).
    directions = (eigvec.T @ z) / eigval.sqrt()[:, None]
    components = directions * (eigval / n).sqrt()[:, None]
    components = components.float().reshape(found, p * c, resolution, resolution) * per_channel
    return mean, torch.cat([components, components.new_zeros(k - found, *components.shape[1:])])


# --------------------------------------------------------------------------------------------------
# The student: encoder + decoder + super-resolution
# --------------------------------------------------------------------------------------------------


def render_views(
    planes: Tensor,
    decoder: Sequence[Tensor],
    cameras: Tensor,
    config: TrainConfig,
    scene: SceneBounds,
    *,
    resolution: int | None = None,
) -> dict[str, Tensor]:
    """:func:`~lp3d.render_torch.render_torch` of planes (B, 3, 32, T, T) from cameras (B, 25) with a
    training configuration's sample counts (at ``raw_resolution`` unless ``resolution`` is given)."""
    return render_torch(
        planes,
        *decoder,
        cameras,
        resolution=resolution or config.raw_resolution,
        depth_resolution=config.depth_resolution,
        depth_resolution_importance=config.depth_resolution_importance,
        ray_start=scene.ray_start,
        ray_end=scene.ray_end,
        box_warp=scene.box_warp,
    )


class TriplaneDecoder(nn.Module):
    """EG3D's OSGDecoder as effective weights w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,)."""

    def __init__(self, w0: np.ndarray, b0: np.ndarray, w1: np.ndarray, b1: np.ndarray) -> None:
        super().__init__()
        self.w0 = nn.Parameter(torch.as_tensor(np.asarray(w0, np.float32)).clone())
        self.b0 = nn.Parameter(torch.as_tensor(np.asarray(b0, np.float32)).clone())
        self.w1 = nn.Parameter(torch.as_tensor(np.asarray(w1, np.float32)).clone())
        self.b1 = nn.Parameter(torch.as_tensor(np.asarray(b1, np.float32)).clone())

    def weights(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.w0, self.b0, self.w1, self.b1


class Student(nn.Module):
    """E, its decoder and its SR. ``encode(image (B,3,S,S)) -> planes (B,3,32,T,T)``;
    ``render(planes, cameras (B,25)) -> ViewRenders`` (features (B,32,r,r), high (B,3,S,S),
    depth (B,r,r)).

    With ``config.mean_triplane_offset`` the triplane is ``E(I) + plane_offset``, a learned
    (3, 32, T, T) offset (see :class:`TrainConfig`); otherwise ``plane_offset`` is None.
    """

    def __init__(
        self,
        config: TrainConfig,
        decoder: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        scene: SceneBounds,
    ) -> None:
        super().__init__()
        self.config = config
        self.scene = scene
        self.encoder = LP3DEncoder(config.encoder)
        self.decoder = TriplaneDecoder(*decoder)
        self.superres = SuperResolution(config.superres)
        if config.mean_triplane_offset:
            t, c = config.triplane_resolution, config.encoder.plane_channels
            self.plane_offset = nn.Parameter(torch.zeros(3, c, t, t))
        else:
            self.register_parameter("plane_offset", None)

    def encode(self, image: Tensor, *, amp: bool = False) -> Tensor:
        with torch.autocast(image.device.type, dtype=torch.float16, enabled=amp):
            planes = self.encoder(image)
        planes = planes.float()
        return planes if self.plane_offset is None else planes + self.plane_offset

    @torch.no_grad()
    def start_from_mean(self, mean_planes: Tensor) -> None:
        """Set ``plane_offset`` to a mean teacher triplane (3, 32, T, T) and zero the encoder's last
        convolution, so that the untrained student outputs exactly the mean triplane."""
        if self.plane_offset is None:
            raise ValueError("start_from_mean needs config.mean_triplane_offset")
        self.plane_offset.copy_(mean_planes.to(self.plane_offset))
        last = self.encoder.head.out_convs[-1]
        assert isinstance(last, nn.Conv2d)
        last.weight.zero_()
        if last.bias is not None:
            last.bias.zero_()

    def render(
        self,
        planes: Tensor,
        cameras: Tensor,
        *,
        resolution: int | None = None,
        freeze_superres: bool = False,
    ) -> ViewRenders:
        """Render planes (B, 3, 32, T, T) from cameras (B, 25). ``freeze_superres``: gradients reach
        the planes through the SR but not the SR's parameters (stage 1, where the paper's SR is frozen)."""
        out = render_views(
            planes, self.decoder.weights(), cameras, self.config, self.scene, resolution=resolution
        )
        features = out["features"]
        if self.config.recipe == "cpu":
            # No SR in the CPU recipe: the final image is a volume render at the image size, as the
            # procedural teacher's is (and as ``lp3d render`` draws an encoded triplane).
            high = render_views(
                planes,
                self.decoder.weights(),
                cameras,
                self.config,
                self.scene,
                resolution=self.config.image_size,
            )["rgb"]
            return ViewRenders(features=features, high=high, depth=out["depth"])
        if freeze_superres:
            frozen = {k: v.detach() for k, v in self.superres.named_parameters()}
            high = torch.func.functional_call(self.superres, frozen, (features,))
        else:
            high = self.superres(features)
        return ViewRenders(features=features, high=high, depth=out["depth"])

    def triplane(
        self, planes: Tensor, *, camera: np.ndarray | None = None, source: str | None = None
    ) -> TriplaneData:
        """One encoded triplane (3, 32, T, T) as a self-contained :class:`TriplaneData`."""
        w = [t.detach().cpu().numpy() for t in self.decoder.weights()]
        return TriplaneData(
            planes=planes.detach().float().cpu().numpy(),
            w0=w[0],
            b0=w[1],
            w1=w[2],
            b1=w[3],
            box_warp=self.scene.box_warp,
            ray_start=self.scene.ray_start,
            ray_end=self.scene.ray_end,
            camera=camera,
            source=source,
        )


def render_teacher(
    teacher: Teacher,
    planes: Tensor,
    decoder: Sequence[Tensor],
    cameras: Tensor,
    config: TrainConfig,
    scene: SceneBounds,
    *,
    raw: bool = True,
    high: bool = True,
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """The teacher's ``(features (B,32,r,r), depth (B,r,r), high (B,3,S,S))`` for cameras (B, 25).

    ``high`` is the teacher's super-resolution of its raw render when it has one (``superresolve``,
    EG3D; resized to S with antialiasing when its output differs, e.g. 512 -> 128 for a CPU
    configuration), else a direct volume render at the image size (procedural). Parts not asked for
    are None.
    """
    sr = getattr(teacher, "superresolve", None)
    features = depth = image = None
    with torch.no_grad():
        if raw or (high and sr is not None):
            out = render_views(planes, decoder, cameras, config, scene)
            features, depth = out["features"], out["depth"]
        if high:
            if sr is not None:
                image = sr(features).to(planes.device, torch.float32)
                s = config.image_size
                if image.ndim == 4 and tuple(image.shape[-2:]) != (s, s):
                    image = F.interpolate(image, size=(s, s), mode="bilinear", antialias=True)
            else:
                image = render_views(planes, decoder, cameras, config, scene, resolution=config.image_size)
                image = image["rgb"]
    return features, depth, image


# --------------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------------


def _atomic_torch_save(obj: dict[str, Any], path: Path) -> None:
    """torch.save that never leaves a half-written checkpoint."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _atomic_write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def load_checkpoint(
    path: str | os.PathLike[str], *, map_location: str | torch.device = "cpu"
) -> dict[str, Any]:
    """Read a training checkpoint (a run directory means its latest); never unpickles code.

    Returns the raw dict with ``config`` parsed into a :class:`TrainConfig` under ``"train_config"``.
    For a run directory, an unreadable newest checkpoint (a kill or a full disk mid-copy) is skipped
    with a warning in favour of the newest readable one.

    Raises:
        CheckpointError: not a file, not an lp3d checkpoint, another format version.
    """
    p = Path(path)
    if p.is_dir():
        return newest_readable(p, lambda f: load_checkpoint(f, map_location=map_location), CheckpointError)
    if not p.is_file():
        raise CheckpointError(f"checkpoint {str(p)!r}: no such file")
    try:
        ckpt = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as e:
        raise CheckpointError(f"checkpoint {str(p)!r} cannot be read as a plain state dict: {e}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        got = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(
            f"{str(p)!r} is not an lp3d training checkpoint of format {CHECKPOINT_FORMAT!r} (got {got!r})"
        )
    try:
        ckpt["train_config"] = TrainConfig.from_json(ckpt["config"])
    except (ValueError, TypeError, KeyError) as e:
        raise CheckpointError(f"{str(p)!r}: its configuration cannot be read by this version: {e}") from None
    ckpt["path"] = str(p)
    return ckpt


def _load_shared_checkpoint(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> dict[str, Any]:
    """:func:`load_checkpoint` on every rank of the same file: under torchrun rank 0 picks it (a run
    directory means its newest readable checkpoint) and tells the others which."""
    if distributed.is_main():
        ckpt = load_checkpoint(path, map_location=device)
        distributed.broadcast_object(ckpt["path"])
        return ckpt
    return load_checkpoint(distributed.broadcast_object(""), map_location=device)


def _rank_seed(seed: int, rank: int, step: int) -> int:
    """The torch seed of a rank other than 0 (its own dropout masks), from the run's seed, the rank and
    the step it starts its streams at; rank 0 keeps the single-process streams."""
    return int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0])


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


#: Settings of how a run is kept, not of what it computes: a resumed run may change them.
RUN_KEEPING_FIELDS = frozenset({"checkpoint_every", "keep_checkpoints", "sample_every"})


def config_differences(a: TrainConfig, b: TrainConfig) -> list[str]:
    """``["field: a != b", ...]`` over the flattened JSON of two configs, leaving out
    :data:`RUN_KEEPING_FIELDS`."""
    fa, fb = _flatten(a.to_dict()), _flatten(b.to_dict())
    keys = sorted((set(fa) | set(fb)) - RUN_KEEPING_FIELDS)
    return [f"{k}: {fa.get(k)!r} != {fb.get(k)!r}" for k in keys if fa.get(k) != fb.get(k)]


def student_from_checkpoint(ckpt: dict[str, Any], device: torch.device | str = "cpu") -> Student:
    """Rebuild the student of a checkpoint (from :func:`load_checkpoint`) in eval mode."""
    cfg: TrainConfig = ckpt["train_config"]
    scene = SceneBounds(**json.loads(ckpt["scene"]))
    dec = ckpt["student"]
    decoder = tuple(dec[f"decoder.{n}"].cpu().numpy() for n in ("w0", "b0", "w1", "b1"))
    student = Student(cfg, decoder, scene)  # type: ignore[arg-type]
    try:
        student.load_state_dict(ckpt["student"])
    except RuntimeError as e:
        raise CheckpointError(f"checkpoint weights do not fit configuration {cfg.name!r}: {e}") from None
    return student.to(device).eval()


# --------------------------------------------------------------------------------------------------
# The trainer
# --------------------------------------------------------------------------------------------------


def _rng_states() -> dict[str, Any]:
    py = random.getstate()
    np_state = np.random.get_state()  # noqa: NPY002  (the global state other code may use)
    out: dict[str, Any] = {
        "python": json.dumps([py[0], list(py[1]), py[2]]),
        "numpy": json.dumps(
            [
                np_state[0],
                np.asarray(np_state[1]).tolist(),
                int(np_state[2]),
                int(np_state[3]),
                float(np_state[4]),
            ]
        ),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def _set_rng_states(states: dict[str, Any]) -> None:
    v, s, g = json.loads(states["python"])
    random.setstate((v, tuple(s), g))
    n = json.loads(states["numpy"])
    legacy = (n[0], np.asarray(n[1], dtype=np.uint32), n[2], n[3], n[4])
    np.random.set_state(legacy)  # noqa: NPY002
    torch.set_rng_state(states["torch"].cpu())
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([t.cpu() for t in states["cuda"]])


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


class Trainer:
    """Owns the models, optimisers, data stream and run directory of one training run.

    Args:
        config: the run's configuration (on resume it must equal the checkpoint's).
        out_dir: the run directory (``config.json``, ``log.csv``, ``checkpoints/``, ``samples/``).
        teacher: the frozen teacher; its name is recorded for evaluation.
        teacher_name: ``procedural`` or ``eg3d``.
        perceptual: the perceptual loss module (see :func:`lp3d.losses.build_perceptual`).
        device: where to train.
        resume: a checkpoint file or run directory to continue from.
        category: optional category-loss hook (``LossWeights.category`` must be > 0 to use it).
        progress: progress bars (training, dataset synthesis).
        data_cache: where the CPU recipe's synthetic dataset is cached
            (default :func:`lp3d.synthetic_data.default_cache_root`).
        teacher_args: how the teacher was built (:data:`TEACHER_ARGS`), recorded in the checkpoints so
            ``--resume`` and ``lp3d.eval`` can rebuild it (default: the resumed checkpoint's).
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
        # Under torchrun (lp3d.distributed): this process's place, and its share of the global batch.
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

    # -- data --------------------------------------------------------------------------------------
    def dataset_key(self) -> DatasetKey:
        """The cache key of this run's synthetic dataset (CPU recipe)."""
        return dataset_key(self.config, self.teacher, self.teacher_name)

    def _input_renderer(self) -> Callable[[Tensor, Tensor], Tensor]:
        """The teacher's render of the encoder's input, exactly as the evaluation makes it."""
        cfg = self.config

        def render(planes: Tensor, cameras: Tensor) -> Tensor:
            planes, cameras = planes.to(self.device), cameras.to(self.device, torch.float32)
            dec = self.teacher_decoder
            _, _, image = render_teacher(self.teacher, planes, dec, cameras, cfg, self.scene, raw=False)
            assert image is not None
            return image.float().cpu()

        return render

    def open_dataset(self) -> SyntheticDataset:
        """Load this run's cached dataset, synthesising it first when absent or invalid."""
        return SyntheticDataset.open(
            self.dataset_key(),
            self.teacher,
            self._input_renderer(),
            root=self.data_cache,
            progress=self.progress,
        )

    def _teacher_planes(self, tris: list[TriplaneData]) -> Tensor:
        planes = torch.from_numpy(np.stack([t.planes.astype(np.float32) for t in tris])).to(self.device)
        return planes

    def synthesize(self, step: int) -> Batch:
        """Identities, cameras and teacher renders of ``step`` (all randomness from ``data_rng``).

        Under torchrun the whole global batch is drawn and this rank keeps its rows (``shard``), so the
        stream does not depend on the number of processes; only this rank's rows are rendered."""
        cfg = self.config
        b = cfg.batch_size
        seeds = [int(s) for s in self.data_rng.integers(cfg.train_seeds[0], cfg.train_seeds[1], size=b)]
        ref_labels = sample_cameras(cfg.reference_cameras, b, self.data_rng).labels
        mv_labels = sample_cameras(cfg.multiview_cameras, b, self.data_rng).labels
        seeds, ref_labels, mv_labels = (self._shard(x) for x in (seeds, ref_labels, mv_labels))
        ref_cams = torch.from_numpy(np.ascontiguousarray(ref_labels))
        mv_cams = torch.from_numpy(np.ascontiguousarray(mv_labels))
        ref_cams = ref_cams.to(self.device, torch.float32)
        mv_cams = mv_cams.to(self.device, torch.float32)
        planes = self._teacher_planes(self.teacher.sample_batch(seeds))
        is_ref = cfg.reference_step(step)
        dec = self.teacher_decoder
        f_ref, d_ref, ref_image = render_teacher(
            self.teacher, planes, dec, ref_cams, cfg, self.scene, raw=is_ref, high=True
        )
        f_mv, d_mv, h_mv = render_teacher(self.teacher, planes, dec, mv_cams, cfg, self.scene)
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

    def _shard(self, x: Any) -> Any:
        """This rank's rows of a global batch (everything in one process)."""
        return distributed.shard(x, rank_=self.rank, size=self.world_size)

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

    def mean_teacher_planes(self, n: int) -> Tensor:
        """Mean (3, 32, T, T) of the teacher triplanes of the first ``n`` training seeds."""
        lo = self.config.train_seeds[0]
        total = None
        for seed in range(lo, lo + n):
            p = self._teacher_planes([self.teacher.sample(seed)])
            total = p if total is None else total + p
        assert total is not None
        return self._teacher_target_planes(total / n)[0]

    def _teacher_target_planes(self, planes: Tensor) -> Tensor:
        """Teacher planes at the student's triplane resolution (for L_tri)."""
        return resize_planes(planes, self.config.triplane_resolution)

    # -- one step ----------------------------------------------------------------------------------
    def train_step(self, batch: Batch | None = None) -> dict[str, Any]:
        """Run step ``self.step`` (synthesising its batch unless given) and advance; returns the log row."""
        cfg = self.config
        step = self.step
        t0 = time.perf_counter()
        if cfg.recipe == "cpu":
            row = self._cpu_step(step)
            self.step += 1
            self._mean_over_ranks(row)
            row["seconds"] = time.perf_counter() - t0
            return row
        stage = cfg.stage(step)
        self._set_trainable(step)
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
            tri = self.losses.triplane(planes, self._teacher_target_planes(batch.planes))
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
        ref_s = None
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
                f"step {step}: the training loss is {float(total)} (terms {terms}, identity seeds "
                f"{batch.seeds}); resume from the last checkpoint with a lower learning rate"
            )
        self._student_step(total, row)

        if use_d:
            row.update(self._discriminator_step(step, batch, rendered, is_ref))
        self.step += 1
        self._mean_over_ranks(row)
        row["seconds"] = time.perf_counter() - t0
        return row

    def _mean_over_ranks(self, row: dict[str, Any]) -> None:
        """Under torchrun: the logged losses become their means over the ranks (each is a mean over
        an equal share of the batch, so this is the global batch's mean)."""
        if self.world_size > 1:
            row.update(
                distributed.mean_over_ranks(
                    {k: v for k, v in row.items() if isinstance(v, float)}, self.device
                )
            )

    def _student_step(self, total: Tensor, row: dict[str, Any]) -> None:
        """Backward ``total``, average the gradients over the ranks (torchrun), clip, one optimiser and
        scheduler step; logs the loss and rate in ``row``."""
        self.opt_g.zero_grad(set_to_none=True)
        self.scaler.scale(total).backward()
        distributed.average_gradients(self.student.parameters())
        if self.config.grad_clip > 0:
            self.scaler.unscale_(self.opt_g)
            torch.nn.utils.clip_grad_norm_(self.student.parameters(), self.config.grad_clip)
        self.scaler.step(self.opt_g)
        self.scaler.update()
        self.sched_g.step()
        row["loss"] = float(total.detach())
        row["lr"] = float(self.opt_g.param_groups[0]["lr"])

    def _cpu_step(self, step: int) -> dict[str, Any]:
        """One step of the CPU recipe: a batch of cached identities, normalised L_tri, and after
        ``regression_steps`` the RGB L1 of random rays of their cached teacher views."""
        cfg, ds = self.config, self.dataset
        assert ds is not None
        self._set_trainable(step)
        self.student.train()
        # The global batch's rows and flips, of which this rank keeps its share (torchrun).
        idx = np.sort(self.data_rng.integers(0, len(ds), size=cfg.batch_size))
        flips = self.data_rng.random(len(idx)) < 0.5 if cfg.mirror_augment else None
        idx = self._shard(idx)
        image = torch.from_numpy(ds.ref_image[idx].astype(np.float32)).to(self.device)
        target = torch.from_numpy(ds.planes[idx].astype(np.float32)).to(self.device)
        if flips is not None:  # a flipped input is the mirrored head: twice the identities for free
            flip = torch.from_numpy(np.ascontiguousarray(self._shard(flips))).to(self.device)
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
            pred, want = self._random_ray_rgb(planes, target)
            ray = l1(pred, want, name="ray rgb")
            total = total + cfg.ray_weight * ray
            row["ray"] = float(ray.detach())
        if not bool(torch.isfinite(total)):
            raise NonFiniteError(
                f"step {step}: the training loss is {float(total)} (terms {row}, dataset rows "
                f"{idx.tolist()}); resume from the last checkpoint with a lower learning rate"
            )
        self._student_step(total, row)
        return row

    @torch.no_grad()
    def heldout_metrics(self) -> dict[str, float]:
        """The learning curve's point: novel-view RGB PSNR of ``heldout_identities`` held-out
        identities (seeds from ``eval_seed_start``) against their own teacher and against the other
        held-out identities' teachers, and the difference (identity specificity, 0 dB for a student
        that ignores its input). Raw renders at ``raw_resolution`` from yaw -30° and +30° (pitch 10°);
        the teacher is the training teacher (``python -m lp3d.eval`` scores against the native one)."""
        from lp3d.camera import look_at_camera

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

    def _random_ray_rgb(self, planes: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
        """RGB (B, M, 3) of the student's planes and of the teacher's ``target`` planes on M random
        pixel rays of one random multiview camera per identity (drawn from ``data_rng`` for the global
        batch, of which this rank keeps its rows)."""
        cfg = self.config
        b, m, r = cfg.batch_size, cfg.rays_per_identity, cfg.raw_resolution
        cams = torch.from_numpy(
            np.ascontiguousarray(self._shard(sample_cameras(cfg.multiview_cameras, b, self.data_rng).labels))
        )
        pixels = self.data_rng.integers(0, r * r, size=(b, m))
        pixels = torch.from_numpy(np.ascontiguousarray(self._shard(pixels))).to(self.device)
        origins, directions = rays_from_cameras(cams.to(self.device, torch.float32), r)
        gather = pixels.unsqueeze(-1).expand(-1, -1, 3)
        origins, directions = origins.gather(1, gather), directions.gather(1, gather)

        def rgb(p: Tensor, decoder: Sequence[Tensor]) -> Tensor:
            out = render_rays(
                p,
                *decoder,
                origins,
                directions,
                ray_start=self.scene.ray_start,
                ray_end=self.scene.ray_end,
                box_warp=self.scene.box_warp,
                depth_resolution=cfg.depth_resolution,
                depth_resolution_importance=cfg.depth_resolution_importance,
            )
            return out["features"][..., :3]

        with torch.no_grad():
            want = rgb(target, self.teacher_decoder)
        return rgb(planes, self.student.decoder.weights()), want

    def _discriminator_step(
        self, step: int, batch: Batch, fake: ViewRenders, is_ref: bool
    ) -> dict[str, float]:
        """Teacher renders are real, student renders fake (paper §3.2: no real photographs)."""
        cfg = self.config
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
        self.opt_d.zero_grad(set_to_none=True)
        loss.backward()
        distributed.average_gradients(self.discriminator.parameters())
        self.opt_d.step()
        self.sched_d.step()
        self.discriminator.requires_grad_(False)
        return out

    # -- previews ----------------------------------------------------------------------------------
    @torch.no_grad()
    def save_samples(
        self, seeds: Sequence[int] | None = None, yaws: Sequence[float] = (-30.0, 0.0, 30.0)
    ) -> Path:
        """``samples/step-NNNNNN.png``: per held-out identity, a teacher row (input, views at ``yaws``)
        and a student row (its input-view render, the same views)."""
        from lp3d.camera import look_at_camera
        from lp3d.images import rgb_to_uint8, save_png, tile

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


# --------------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------------


#: ``--help``'s description (``python -m lp3d.train`` and ``lp3d train``).
DESCRIPTION = "Distil a teacher into the LP3D triplane encoder (paper §3.2)."


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The training options, shared by ``python -m lp3d.train`` and ``lp3d train``."""
    p.add_argument(
        "--config",
        choices=sorted(TRAIN_CONFIGS),
        help="named configuration (default tiny; on --resume, the checkpoint's)",
    )
    p.add_argument("--teacher", choices=TEACHERS, default=None, help="teacher (default procedural)")
    p.add_argument(
        "--teacher-pkl",
        default=None,
        help="EG3D generator pickle for --teacher eg3d (remembered on --resume)",
    )
    p.add_argument(
        "--eg3d-source",
        default=None,
        help="NVlabs/eg3d's source, to unpickle the generator: the repository root or its inner eg3d/ "
        "folder (the one holding torch_utils/, dnnlib/ and training/); not needed when those are "
        "importable already (remembered on --resume)",
    )
    p.add_argument(
        "--eg3d-conditioning",
        choices=("gen_videos", "gen_samples"),
        default=None,
        help="whose conditioning camera the EG3D mapping gets: gen_videos.py's (LookAtPoseSampler(3.14/2, "
        "3.14/2), focal 4.2647; default) or gen_samples.py's (exactly frontal, focal 4.26339)",
    )
    p.add_argument("--out", default=None, help="run directory (default runs/<config>)")
    p.add_argument("--max-steps", type=int, default=None, help="stop at this global step (default: config)")
    p.add_argument("--batch", type=int, default=None, help="batch size (overrides the config)")
    p.add_argument(
        "--total-steps",
        type=int,
        default=None,
        help="rescale the config's schedule (stage boundaries keep the paper's proportions) to this length",
    )
    p.add_argument("--resume", default=None, help="checkpoint file or run directory to continue from")
    p.add_argument(
        "--perceptual",
        choices=PERCEPTUAL_KINDS,
        default=None,
        help="perceptual loss (default: the config's; lpips needs backbone weights on disk)",
    )
    p.add_argument("--lpips-weights", default=None, help="torchvision VGG16/AlexNet state dict for LPIPS")
    p.add_argument(
        "--data-cache",
        default=None,
        help="folder of the CPU recipe's cached synthetic datasets (default $LP3D_DATA_CACHE, "
        "$LP3D_CACHE/datasets or ~/.cache/lp3d/datasets)",
    )
    p.add_argument(
        "--dataset-identities",
        type=int,
        default=None,
        help="identities in the CPU recipe's synthetic dataset (overrides the config)",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=None,
        help="write a checkpoint every N steps (default: the config's; may change on --resume)",
    )
    p.add_argument(
        "--device",
        default="auto",
        help="cpu, cuda, cuda:N or auto; under torchrun each process takes cuda:LOCAL_RANK (cuda:N is "
        "refused) or the CPU",
    )
    p.add_argument(
        "--dist-timeout",
        type=float,
        default=60.0,
        metavar="MINUTES",
        help="under torchrun, how long a process waits for the others at a collective call (default 60; "
        "it must cover rank 0 synthesising a missing dataset)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser(prog: str = "python -m lp3d.train") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=run_cli)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.train`` (an alias of ``lp3d train``); the exit status is :mod:`lp3d.errors`'
    policy: 0 done, 1 an error (printed as one line), 2 a usage error, 130 interrupted."""
    return run_command(build_parser(), argv)


def run_cli(args: argparse.Namespace) -> int:
    """Train with parsed :func:`add_arguments` options; returns the exit status."""
    try:
        return _main(args)
    finally:
        distributed.shutdown()  # leaves torchrun's process group (a no-op for one process)


def _main(args: argparse.Namespace) -> int:
    # Errors are printed by every process (one rank may fail alone); under torchrun they name the rank.
    def error(e: BaseException | str) -> None:
        where = f" (rank {distributed.rank()})" if distributed.world_size() > 1 else ""
        print(f"error{where}: {e}", file=sys.stderr)

    try:
        if not (math.isfinite(args.dist_timeout) and args.dist_timeout > 0):
            raise ValueError(f"--dist-timeout must be a positive number of minutes, got {args.dist_timeout}")
        device = distributed.setup(args.device, timeout_minutes=args.dist_timeout).device
        ckpt = _load_shared_checkpoint(args.resume) if args.resume else None
        if ckpt is not None:
            cfg: TrainConfig = ckpt["train_config"]
            if args.config is not None and args.config != cfg.name:
                raise CheckpointError(
                    f"--resume {args.resume}: the checkpoint was trained with configuration {cfg.name!r}, "
                    f"not {args.config!r}; omit --config to resume it"
                )
            teacher_name = args.teacher or ckpt["teacher"]
            out = Path(args.out) if args.out else Path(ckpt["path"]).parent.parent
        else:
            cfg = TRAIN_CONFIGS[args.config or "tiny"]
            teacher_name = args.teacher or "procedural"
            out = Path(args.out) if args.out else Path("runs") / cfg.name
        if args.batch is not None:
            cfg = dataclasses.replace(cfg, batch_size=args.batch)
        if args.total_steps is not None:
            if ckpt is not None and args.total_steps != cfg.total_steps:
                raise CheckpointError(
                    f"--total-steps {args.total_steps}: the checkpoint's schedule has {cfg.total_steps} "
                    "steps; a resumed run keeps its schedule"
                )
            if args.total_steps < 1:
                raise ValueError(f"--total-steps must be >= 1, got {args.total_steps}")
            cfg = dataclasses.replace(cfg, **_scaled_schedule(args.total_steps, cfg))
        if args.perceptual is not None:
            cfg = dataclasses.replace(cfg, perceptual=args.perceptual)
        if args.checkpoint_every is not None:
            if args.checkpoint_every < 1:
                raise ValueError(f"--checkpoint-every must be >= 1, got {args.checkpoint_every}")
            cfg = dataclasses.replace(cfg, checkpoint_every=args.checkpoint_every)
        if args.dataset_identities is not None:
            if ckpt is not None and args.dataset_identities != cfg.dataset_identities:
                raise CheckpointError(
                    f"--dataset-identities {args.dataset_identities}: the checkpoint was trained on "
                    f"{cfg.dataset_identities}; a resumed run keeps its dataset"
                )
            cfg = dataclasses.replace(cfg, dataset_identities=args.dataset_identities)
        perceptual = build_perceptual(
            cfg.perceptual, lpips_net=cfg.lpips_net, lpips_weights=args.lpips_weights
        )
        if perceptual is not None:
            perceptual = perceptual.to(device)
        targs = resolve_teacher_args(
            ckpt if ckpt is not None and teacher_name == ckpt["teacher"] else None,
            teacher_pkl=args.teacher_pkl,
            eg3d_source=args.eg3d_source,
            conditioning=args.eg3d_conditioning,
        )
        recorded = resolve_teacher_args(ckpt) if ckpt is not None else None
        if recorded is not None and _recordable(targs) != recorded:  # recorded paths are absolute
            if targs["conditioning"] != recorded["conditioning"]:
                raise CheckpointError(
                    f"--eg3d-conditioning {targs['conditioning']}: the run was trained with "
                    f"{recorded['conditioning']!r}; a resumed run keeps its teacher"
                )
            distributed.note(f"note: teacher arguments differ from the run's recorded ones: {targs}")
        teacher = build_teacher(
            teacher_name,
            triplane_resolution=cfg.triplane_resolution,
            teacher_pkl=targs["teacher_pkl"],
            eg3d_source=targs["eg3d_source"],
            conditioning=targs["conditioning"],  # type: ignore[arg-type]
            device=device,
        )
        trainer = Trainer(
            cfg,
            out,
            teacher=teacher,
            teacher_name=teacher_name,
            perceptual=perceptual,
            device=device,
            resume=ckpt["path"] if ckpt is not None else None,
            progress=not args.no_progress,
            data_cache=args.data_cache,
            teacher_args=targs,
        )
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        error(e)
        return EXIT_ERROR
    distributed.note(
        f"training {cfg.name!r} on {device} with the {teacher_name} teacher, batch {cfg.batch_size}, "
        f"from step {trainer.step} to {args.max_steps or cfg.total_steps}; run directory {out}"
    )
    try:
        trainer.train(args.max_steps)
    except NonFiniteError as e:
        error(e)
        return EXIT_ERROR
    except KeyboardInterrupt:
        distributed.note(f"aborted; the last checkpoint is {latest_checkpoint(out)}")
        return EXIT_INTERRUPTED
    if trainer.interrupted:
        last = latest_checkpoint(out) if trainer.is_main else None
        distributed.note(f"interrupted at step {trainer.step}; saved {last}; continue with --resume {out}")
        return EXIT_INTERRUPTED
    if trainer.is_main:
        print(f"done at step {trainer.step}; checkpoint {latest_checkpoint(out)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
