"""How ``--refine`` fits a lifted head to its photo (:class:`RefineSettings`), apart from the fit
itself (:mod:`lp3d.lift.refine`) so that the command line can name its defaults without importing
torch.

May import :mod:`lp3d.render`."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from lp3d.render.settings import RenderSettings

#: Most refinement steps one call may ask for (a typo such as 50000 would run for hours).
MAX_STEPS = 10_000


@dataclass(frozen=True)
class RefineSettings:
    """How :func:`refine` fits a triplane to its photo (module docstring). The defaults are the ones
    ``bench/refine.py`` measured on held-out teacher identities (``bench/RESULTS.md``)."""

    steps: int = 30
    lr: float = 0.03
    prior_weight: float = 0.1
    #: Also fit the photo flipped left to right, seen from the mirrored camera: faces are nearly
    #: symmetric, and the second view holds the side the photo turns away from.
    mirror: bool = True
    resolution: int = 64
    rays_per_step: int = 1024
    depth_resolution: int = 16
    depth_resolution_importance: int = 16
    search_yaws_deg: tuple[float, ...] = (-40.0, -30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 40.0)
    search_pitches_deg: tuple[float, ...] = (-10.0, 0.0, 10.0, 20.0)
    search_resolution: int = 16
    pose_steps: int = 30
    pose_lr: float = 0.02
    pose_resolution: int = 32
    seed: int = 0

    def __post_init__(self) -> None:
        ints = {
            "steps": (0, MAX_STEPS),
            "resolution": (8, 512),
            "rays_per_step": (1, 1 << 20),
            "depth_resolution": (4, 256),
            "depth_resolution_importance": (0, 256),
            "search_resolution": (8, 256),
            "pose_steps": (0, MAX_STEPS),
            "pose_resolution": (8, 256),
            "seed": (0, 2**31 - 1),
        }
        for name, (lo, hi) in ints.items():
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
                raise ValueError(f"RefineSettings.{name} must be an int in [{lo}, {hi}], got {v!r}")
        for name in ("lr", "prior_weight", "pose_lr"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"RefineSettings.{name} must be a finite number >= 0, got {v!r}")
        if not isinstance(self.mirror, bool):
            raise ValueError(f"RefineSettings.mirror must be a bool, got {self.mirror!r}")
        for name in ("search_yaws_deg", "search_pitches_deg"):
            v = getattr(self, name)
            if not v or not all(isinstance(a, (int, float)) and math.isfinite(a) and abs(a) < 90 for a in v):
                raise ValueError(f"RefineSettings.{name} must be a non-empty tuple of angles in (-90, 90)")

    def total_steps(self, pose_known: bool = False) -> int:
        """Optimisation steps of one :func:`refine` (the pose's, unless known, then the planes')."""
        return self.steps + (0 if pose_known else self.pose_steps)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def render_settings(self, resolution: int) -> RenderSettings:
        return RenderSettings(
            resolution=resolution,
            depth_resolution=self.depth_resolution,
            depth_resolution_importance=self.depth_resolution_importance,
        )
