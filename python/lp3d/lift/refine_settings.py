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
    ``bench/refine_sweep.py`` measured on held-out teacher identities (``bench/history/RESULTS.md``,
    "Refinement")."""

    steps: int = 60
    lr: float = 0.03
    prior_weight: float = 0.1
    #: Also fit the photo flipped left to right, seen from the mirrored camera: faces are nearly
    #: symmetric, and the second view holds the side the photo turns away from.
    mirror: bool = True
    #: Move the camera with the planes in the raw steps (six numbers: a turn about the head, the
    #: principal point, the focal length; learning rate ``pose_lr``): planes held at a wrong camera
    #: bend to fit the photo from there. Off: it helps where the lifted head looks like the photo
    #: (the teacher's own heads) and turns real photos' cameras away from their faces
    #: (docs/photos-and-video.md measures both).
    fit_camera: bool = False
    resolution: int = 64
    rays_per_step: int = 1024
    #: The share of ``steps`` (the last ones) that fit the *super-resolved* image, when :func:`refine`
    #: has the package's SR network: the network run on the whole feature image of each view, against
    #: the photo at the network's output side. The raw fit before them gets the colours and shape
    #: cheaply; these get what the raw render at ``resolution`` cannot hold and `lp3d render` shows.
    superres_share: float = 2 / 3
    #: Adam's step size in those steps (the network's gradients are smaller than the raw rays').
    superres_lr: float = 0.05
    #: Samples (coarse, fine) per ray of those whole-image renders.
    superres_samples: tuple[int, int] = (12, 12)
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
        for name in ("lr", "superres_lr", "prior_weight", "pose_lr"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"RefineSettings.{name} must be a finite number >= 0, got {v!r}")
        if not (
            isinstance(self.superres_share, (int, float))
            and not isinstance(self.superres_share, bool)
            and 0 <= self.superres_share <= 1
        ):
            raise ValueError(f"RefineSettings.superres_share must be in [0, 1], got {self.superres_share!r}")
        n = self.superres_samples
        if not (
            isinstance(n, tuple)
            and len(n) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) for v in n)
            and 4 <= n[0] <= 256
            and 0 <= n[1] <= 256
        ):
            raise ValueError(f"RefineSettings.superres_samples must be (coarse 4-256, fine 0-256), got {n!r}")
        for name in ("mirror", "fit_camera"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"RefineSettings.{name} must be a bool, got {getattr(self, name)!r}")
        for name in ("search_yaws_deg", "search_pitches_deg"):
            v = getattr(self, name)
            if not v or not all(isinstance(a, (int, float)) and math.isfinite(a) and abs(a) < 90 for a in v):
                raise ValueError(f"RefineSettings.{name} must be a non-empty tuple of angles in (-90, 90)")

    def total_steps(self, pose_known: bool = False) -> int:
        """Optimisation steps of one :func:`refine` (the pose's, unless known, then the planes')."""
        return self.steps + (0 if pose_known else self.pose_steps)

    def superres_steps(self, has_superres: bool) -> int:
        """How many of ``steps`` fit the super-resolved image (none without the network)."""
        return round(self.steps * self.superres_share) if has_superres else 0

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def render_settings(self, resolution: int, samples: tuple[int, int] | None = None) -> RenderSettings:
        coarse, fine = samples or (self.depth_resolution, self.depth_resolution_importance)
        return RenderSettings(
            resolution=resolution, depth_resolution=coarse, depth_resolution_importance=fine
        )
