"""The configuration of a super-resolution fit (:mod:`lp3d.superres_fit.fit`): :class:`FitConfig`
(every setting, saved in the fit's checkpoint), the choices of :attr:`FitConfig.train_on`, and
:class:`FitError`.

Imports lp3d.nets.superres only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

from lp3d.nets.superres import SuperresConfig

__all__ = ["TRAIN_ON", "FitConfig", "FitError"]

#: What the SR can be trained on (:attr:`FitConfig.train_on`).
TRAIN_ON = ("student", "teacher", "both")


class FitError(ValueError):
    """A fit that cannot run or continue here; the message says what and where."""


@dataclass(frozen=True)
class FitConfig:
    """Everything that defines a fit (saved in its checkpoint). The defaults fit the shipped model
    (64² raw renders -> 256² images), sized for a CPU; see the module docstring."""

    #: Training pairs: ``identities`` teacher identities × ``views`` multiview cameras each.
    identities: int = 72
    views: int = 2
    first_seed: int = 100_000
    #: Held-out pairs (one view each), scored at the end.
    heldout_identities: int = 8
    heldout_first_seed: int = 900_000
    #: The SR's input (the raw feature render) and output sides.
    raw_resolution: int = 64
    output_resolution: int = 256
    #: Samples per ray of the raw render and of the teacher's target (``lp3d render``'s default).
    depth_resolution: int = 48
    depth_resolution_importance: int = 48
    #: Samples per ray of the encoder's input image (the CPU recipe's training data used 16 + 16).
    input_depth_resolution: int = 16
    input_depth_resolution_importance: int = 16
    #: Plane resolution of the procedural teacher (its native 256).
    teacher_resolution: int = 256
    camera_seed: int = 0
    #: The network: one SynthesisBlock (×2) per width.
    block_channels: tuple[int, ...] = (64, 32)
    w_dim: int = 32
    #: Training inputs: ``student``, ``teacher`` or ``both`` raw renders (see the module docstring).
    train_on: str = "both"
    #: Optimisation.
    steps: int = 2500
    batch_size: int = 8
    #: Side of a training crop in raw pixels (its target is ``crop · output/raw`` pixels).
    crop: int = 32
    lr: float = 1e-2
    lr_final_factor: float = 0.05
    perceptual_weight: float = 1.0
    seed: int = 0
    checkpoint_every: int = 500

    def __post_init__(self) -> None:
        self.validate()

    @property
    def scale(self) -> int:
        return self.output_resolution // self.raw_resolution

    def superres_config(self) -> SuperresConfig:
        return SuperresConfig(
            name=f"fit-{self.raw_resolution}-{self.output_resolution}",
            input_resolution=self.raw_resolution,
            output_resolution=self.output_resolution,
            block_channels=self.block_channels,
            w_dim=self.w_dim,
            use_noise=False,
        )

    def validate(self) -> None:
        for name in (
            "identities",
            "views",
            "heldout_identities",
            "raw_resolution",
            "output_resolution",
            "depth_resolution",
            "input_depth_resolution",
            "teacher_resolution",
            "w_dim",
            "steps",
            "batch_size",
            "crop",
            "checkpoint_every",
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"FitConfig.{name} must be a positive int, got {v!r}")
        for name in (
            "first_seed",
            "heldout_first_seed",
            "camera_seed",
            "seed",
            "depth_resolution_importance",
            "input_depth_resolution_importance",
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"FitConfig.{name} must be an int >= 0, got {v!r}")
        lo, hi = self.first_seed, self.first_seed + self.identities
        if lo < self.heldout_first_seed + self.heldout_identities and self.heldout_first_seed < hi:
            raise ValueError("FitConfig: the training and held-out seed ranges overlap")
        if self.crop > self.raw_resolution:
            raise ValueError(
                f"FitConfig.crop ({self.crop}) must be <= raw_resolution ({self.raw_resolution})"
            )
        for name in ("lr", "lr_final_factor", "perceptual_weight"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"FitConfig.{name} must be a finite number >= 0, got {v!r}")
        if self.train_on not in TRAIN_ON:
            raise ValueError(f"FitConfig.train_on must be one of {list(TRAIN_ON)}, got {self.train_on!r}")
        self.superres_config()  # sizes: output = raw × 2^k, one width per ×2

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FitConfig:
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"FitConfig.from_dict: unknown keys {unknown}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()})
