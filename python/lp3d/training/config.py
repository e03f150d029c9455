"""Training configurations: :class:`TrainConfig`, the stage loss weights and the named
:data:`TRAIN_CONFIGS` (the paper's ``full``/``lt`` and the CPU recipe's ``small``/``tiny``), and
:func:`config_differences` (what a resume compares).

The first module of :mod:`lp3d.training`: it imports no other module of the package."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, fields
from typing import Any

from lp3d.nets.discriminator import DISCRIMINATOR_CONFIGS, DiscriminatorConfig
from lp3d.nets.encoder import CONFIGS as ENCODER_CONFIGS
from lp3d.nets.encoder import EncoderConfig
from lp3d.nets.superres import SUPERRES_CONFIGS, SuperresConfig
from lp3d.render.settings import RenderSettings
from lp3d.training.camera_sampling import FFHQ_MULTIVIEW, FFHQ_REFERENCE, CameraDistribution
from lp3d.training.losses import PERCEPTUAL_KINDS, LossWeights

RECIPES = ("paper", "cpu")


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

    def render_settings(self, resolution: int | None = None) -> RenderSettings:
        """The renderer settings of this configuration's renders (at ``raw_resolution`` unless
        ``resolution`` is given): its sample counts, deterministic, exact."""
        return RenderSettings(
            resolution=resolution or self.raw_resolution,
            depth_resolution=self.depth_resolution,
            depth_resolution_importance=self.depth_resolution_importance,
        )

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


def scaled_schedule(total: int, base: TrainConfig | None = None) -> dict[str, int]:
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
        **scaled_schedule(total_steps),
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
    sizes: str = "",
) -> TrainConfig:
    """The CPU recipe (``recipe="cpu"``, see :class:`TrainConfig`) at the ``name`` network sizes."""
    return dataclasses.replace(
        _cpu_config(
            name,
            sizes=sizes,
            samples=samples,
            batch_size=batch_size,
            total_steps=total_steps,
            lr_rampup_steps=50,
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
        "small", samples=16, batch_size=8, total_steps=1_400, regression_steps=1_400, dataset_identities=2048
    ),
    "tiny": _cpu_recipe_config(
        "tiny", samples=12, batch_size=4, total_steps=1_000, regression_steps=1_000, dataset_identities=512
    ),
    # The paper's two-stage recipe at the small size: the reference row of bench/train_profile.py,
    # against which the CPU recipe's cost is compared.
    "small-paper": _cpu_config(
        "small-paper", sizes="small", samples=16, batch_size=4, total_steps=2_000, lr_rampup_steps=20
    ),
    # The paper's two-stage recipe at the tiny size: what the tests run of the full/lt machinery
    # (reference schedule, SR from teacher pairs, discriminator, R1) on a CPU.
    "tiny-paper": _cpu_config(
        "tiny-paper", sizes="tiny", samples=12, batch_size=2, total_steps=1_000, lr_rampup_steps=10
    ),
}


# ``small`` without its plane generator (a plane basis alone): the generator's ablation.
TRAIN_CONFIGS["small-basis"] = dataclasses.replace(
    TRAIN_CONFIGS["small"], name="small-basis", encoder=ENCODER_CONFIGS["small-basis"]
)
# ``small`` and ``tiny`` with the input's colour grid in the basis's and generator's codes
# (``small-colour`` is the shipped model's).
for _name in ("small", "tiny"):
    TRAIN_CONFIGS[f"{_name}-colour"] = dataclasses.replace(
        TRAIN_CONFIGS[_name], name=f"{_name}-colour", encoder=ENCODER_CONFIGS[f"{_name}-colour"]
    )


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
