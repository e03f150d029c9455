"""Rendering settings and scene bounds: the one Python definition of each.

:class:`RenderSettings` (with its :class:`Skips`) says how to render; :class:`SceneBounds` where the
scene is (``box_warp``, ``ray_start``, ``ray_end``: stored in the triplane file, because they belong to
the scene). The three renderers take both. Field names follow EG3D's ``rendering_kwargs`` and are the
same in the Rust ``RenderSettings``/``Skips``/``SceneBounds`` structs, the WGSL ``Params`` uniform and
the ``.npz`` keys; ``tests/render/test_render_api.py`` checks the defaults against ``lp3d_render``'s
signatures. Also here: the size caps and EG3D's fixed numerics, one name each.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np

#: Largest ray grid side accepted by every renderer.
MAX_RESOLUTION = 1024
#: Largest coarse or fine sample count per ray (private arrays in the kernel).
MAX_SAMPLES = 256
#: Channels of an EG3D triplane plane / decoder input.
N_CHANNELS = 32
#: Decoder hidden width and output width (density + 32 features).
HIDDEN = 64
N_OUT = 33


#: Largest baked-field points per cell edge (Rust's ``baked::MAX_SUBDIVISIONS``).
MAX_BAKED_SUBDIVISIONS = 8
#: ... and in a two-level field's fine bricks (``baked::MAX_FINE_SUBDIVISIONS``).
MAX_BAKED_FINE_SUBDIVISIONS = 16


@dataclass(frozen=True)
class Skips:
    """Work the renderer may skip, each bounded by a threshold; all 0 (the default) is exact EG3D.
    Rust's ``Skips`` (``crates/renderer/src/settings.rs``) has the same fields. Only the GPU renderer
    implements them: the float64 reference and the torch twin render exact EG3D semantics."""

    #: Early ray termination below this transmittance ...
    transmittance_threshold: float = 0.0
    #: ... and no importance pass for rays whose coarse opacity is below this.
    empty_threshold: float = 0.0
    #: Occupancy grid skip (docs/occupancy.md): intervals between two samples in empty cells of the
    #: triplane's grid have opacity <= this and are taken as 0 without decoding. 0 = off.
    occupancy_epsilon: float = 0.0
    #: ... in the coarse pass too (faster; moves the importance samples, error measured not bounded).
    occupancy_coarse: bool = False
    #: Skip the decoder (docs/baked.md): look samples up in the triplane's baked field, decoded once
    #: at k points per baked cell edge in the cells the occupancy skip keeps (density and RGB
    #: only; needs occupancy_epsilon > 0). 0 = off.
    baked_subdivisions: int = 0
    #: A two-level field (docs/baked.md, "Two levels"): the bricks a surface crosses (or a colour edge
    #: under one) get this many points per cell edge instead, more than baked_subdivisions. 0 = one level.
    baked_fine_subdivisions: int = 0

    @property
    def exact(self) -> bool:
        return self == Skips()

    def validate(self) -> None:
        for name in ("transmittance_threshold", "empty_threshold", "occupancy_epsilon"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {value!r}")
        if self.occupancy_coarse and self.occupancy_epsilon == 0.0:
            raise ValueError("occupancy_coarse needs occupancy_epsilon > 0")
        k = self.baked_subdivisions
        if not _is_int(k) or not 0 <= k <= MAX_BAKED_SUBDIVISIONS:
            raise ValueError(f"baked_subdivisions must be an int in [0, {MAX_BAKED_SUBDIVISIONS}], got {k!r}")
        if k > 0 and self.occupancy_epsilon == 0.0:
            raise ValueError("baked_subdivisions needs occupancy_epsilon > 0")
        fine = self.baked_fine_subdivisions
        if not _is_int(fine) or not (fine == 0 or k < fine <= MAX_BAKED_FINE_SUBDIVISIONS):
            raise ValueError(
                f"baked_fine_subdivisions must be 0 or an int in (baked_subdivisions, "
                f"{MAX_BAKED_FINE_SUBDIVISIONS}], got {fine!r} (baked_subdivisions {k})"
            )
        if fine and k == 0:
            raise ValueError("baked_fine_subdivisions needs baked_subdivisions > 0")


#: The baked field as ``lp3d orbit --baked`` and the viewer's moving frames use it (docs/baked.md):
#: Rust's ``Skips::BAKED`` (tests/render/test_baked.py ties them).
BAKED = Skips(occupancy_epsilon=1e-4, baked_subdivisions=4, baked_fine_subdivisions=10)
#: How many exact 48 + 48 frames a bake of :data:`BAKED` costs, rounded up, on teacher heads and
#: encoder outputs at 128² (bench/history/RESULTS.md, "Two levels, built"). Fewer frames than this
#: render faster exactly; with fewer samples per ray, exact frames are cheaper and the bake pays later.
BAKE_PAYS_AFTER_FRAMES = 15
#: The least PSNR (dB) of a baked frame against the exact one at which ``lp3d orbit --baked auto``
#: keeps the field: about one grey level of an 8-bit frame, below the field's own error against
#: exact 192+192 (docs/performance.md, "What each drag frame looks like").
BAKED_BOUND_DB = 40.0


def bake_pays_after(depth_resolution: int, depth_resolution_importance: int) -> int:
    """Frames an orbit needs before a bake of :data:`BAKED` pays, at these samples per ray:
    :data:`BAKE_PAYS_AFTER_FRAMES` at 48 + 48, scaled up as the exact frame's samples shrink."""
    samples = max(1, depth_resolution + depth_resolution_importance)
    return max(BAKE_PAYS_AFTER_FRAMES, math.ceil(BAKE_PAYS_AFTER_FRAMES * 96 / samples))


@dataclass(frozen=True)
class RenderSettings:
    """How to render (not what): sample counts, resolution, sampling mode and skips; the one settings
    type of the three renderers (:func:`lp3d.render.reference.render_reference`,
    :func:`lp3d.render.torch_twin.render_torch`, :func:`lp3d.render.native.render`).

    ``depth_resolution`` is EG3D's S (coarse samples), ``depth_resolution_importance``
    its N (fine samples; 0 disables the importance pass). Deterministic mode uses no
    coarse jitter and EG3D's ``det=True`` importance draw; ``deterministic=False``
    jitters with the counter-based RNG of ``docs/sampling-rng.md`` seeded by ``seed``.
    """

    resolution: int = 128
    depth_resolution: int = 48
    depth_resolution_importance: int = 48
    white_back: bool = False
    deterministic: bool = True
    seed: int = 0
    skips: Skips = field(default_factory=Skips)

    def validate(self) -> None:
        if not _is_int(self.resolution) or not 1 <= self.resolution <= MAX_RESOLUTION:
            raise ValueError(f"resolution must be an int in [1, {MAX_RESOLUTION}], got {self.resolution!r}")
        s, n = self.depth_resolution, self.depth_resolution_importance
        min_s = 4 if n > 0 else 2
        if not _is_int(s) or not min_s <= s <= MAX_SAMPLES:
            raise ValueError(
                f"depth_resolution must be an int in [{min_s}, {MAX_SAMPLES}] "
                f"(importance sampling needs at least 4), got {s!r}"
            )
        if not _is_int(n) or not (n == 0 or 2 <= n <= MAX_SAMPLES):
            raise ValueError(
                "depth_resolution_importance must be 0 (no importance pass) or an int in "
                f"[2, {MAX_SAMPLES}], got {n!r}"
            )
        if not _is_int(self.seed) or not 0 <= self.seed < 2**32:
            raise ValueError(f"seed must be an int in [0, 2**32), got {self.seed!r}")
        if not isinstance(self.skips, Skips):
            raise ValueError(f"skips must be a Skips, got {type(self.skips).__name__}")
        self.skips.validate()

    def require_exact(self, renderer: str) -> None:
        """Refuse skips in a renderer that implements exact EG3D semantics only."""
        if not self.skips.exact:
            raise ValueError(
                f"{renderer} renders exact EG3D semantics: skips must be all 0, got {self.skips}"
            )

    def native_kwargs(self) -> dict[str, object]:
        """These settings as ``lp3d_render.render``'s keyword arguments (skips flattened, as its
        signature has them; no seed in deterministic mode)."""
        kwargs: dict[str, object] = {
            name: getattr(self, name)
            for name in (
                "resolution",
                "depth_resolution",
                "depth_resolution_importance",
                "white_back",
                "deterministic",
            )
        }
        if not self.deterministic:
            kwargs["seed"] = self.seed
        kwargs.update(asdict(self.skips))
        return kwargs


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


#: EG3D FFHQ scene defaults (stored per triplane file; ``lp3d_render.DEFAULT_*`` agree, a test checks).
DEFAULT_BOX_WARP = 1.0
DEFAULT_RAY_START = 2.25
DEFAULT_RAY_END = 3.3


@dataclass(frozen=True)
class SceneBounds:
    """Where a triplane's scene is: the cube ``[-box_warp/2, box_warp/2]^3`` its planes span and the
    depth range ``[ray_start, ray_end]`` sampled along every ray. Part of the scene, not of a render:
    stored in every triplane file and model package (EG3D's FFHQ values by default). Rust has the same
    type (``SceneBounds`` in ``crates/renderer/src/triplane.rs``)."""

    box_warp: float = DEFAULT_BOX_WARP
    ray_start: float = DEFAULT_RAY_START
    ray_end: float = DEFAULT_RAY_END

    @classmethod
    def of(cls, scene: object) -> SceneBounds:
        """The bounds of anything that has them: a :class:`~lp3d.render.triplane.TriplaneData`, an
        ``lp3d_render.Triplane``, a model package, or a mapping with the three keys."""
        get = scene.get if isinstance(scene, Mapping) else lambda name: getattr(scene, name)
        return cls(float(get("box_warp")), float(get("ray_start")), float(get("ray_end")))

    def problem(self) -> tuple[str, str] | None:
        """``(field, what is wrong)`` for the first bad value, else None. Each value is checked as given
        and as the renderers use it (float32), so ``ray_end = 1e300`` is refused in Python as in Rust."""
        values = {"box_warp": self.box_warp, "ray_start": self.ray_start, "ray_end": self.ray_end}
        as32 = {}
        for name, value in values.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return name, f"must be a real number, got {type(value).__name__}"
            with np.errstate(over="ignore"):
                as32[name] = float(np.float32(value))
            if math.isfinite(value) and not math.isfinite(as32[name]):
                return name, f"{value:e} is not finite as float32 (the renderer's precision)"
        if not (math.isfinite(self.box_warp) and self.box_warp > 0.0 and as32["box_warp"] > 0.0):
            return "box_warp", f"must be finite and > 0 (also as float32), got {self.box_warp!r}"
        if not (math.isfinite(self.ray_start) and self.ray_start >= 0.0):
            return "ray_start", f"must be finite and >= 0, got {self.ray_start!r}"
        if not (
            math.isfinite(self.ray_end)
            and self.ray_end > self.ray_start
            and as32["ray_end"] > as32["ray_start"]
        ):
            start = self.ray_start
            return (
                "ray_end",
                f"must be finite and > ray_start ({start!r}) (also as float32), got {self.ray_end!r}",
            )
        return None

    def validate(self) -> None:
        """Raise a ValueError naming the first bad field (:meth:`problem`)."""
        bad = self.problem()
        if bad is not None:
            raise ValueError(f"{bad[0]}: {bad[1]}")


def _scalar(value: Any) -> Any:
    """A real number given as a NumPy or torch scalar, as a float (anything else unchanged, for
    :meth:`SceneBounds.problem` to name)."""
    if isinstance(value, bool) or isinstance(value, str):
        return value
    if isinstance(value, numbers.Real):
        return float(value)
    if getattr(value, "ndim", None) == 0 and hasattr(value, "item"):
        item = value.item()
        return float(item) if isinstance(item, numbers.Real) and not isinstance(item, bool) else value
    return value


def resolve_settings(
    settings: RenderSettings | None, overrides: Mapping[str, Any], bounds: SceneBounds | None = None
) -> tuple[RenderSettings, SceneBounds]:
    """``(settings, bounds)`` for a renderer call: the given ones (defaults when None) with keyword
    overrides applied (``render_reference(tri, cam, resolution=64)``): a :class:`RenderSettings` field
    changes the settings, a :class:`SceneBounds` field the bounds, anything else is a TypeError. Both
    are validated."""
    settings = RenderSettings() if settings is None else settings
    bounds = SceneBounds() if bounds is None else bounds
    if not isinstance(settings, RenderSettings):
        raise TypeError(f"settings must be a RenderSettings, got {type(settings).__name__}")
    if not isinstance(bounds, SceneBounds):
        raise TypeError(f"bounds must be a SceneBounds, got {type(bounds).__name__}")
    render_fields = {f.name for f in fields(RenderSettings)}
    bounds_fields = {f.name for f in fields(SceneBounds)}
    unknown = sorted(set(overrides) - render_fields - bounds_fields)
    if unknown:
        raise TypeError(f"unknown render argument(s) {', '.join(unknown)}")
    settings = replace(settings, **{k: v for k, v in overrides.items() if k in render_fields})
    bounds = replace(bounds, **{k: _scalar(v) for k, v in overrides.items() if k in bounds_fields})
    settings.validate()
    bounds.validate()
    return settings, bounds


# EG3D's fixed numerics, one name each for the float64 reference and the torch twin (the WGSL
# kernels spell the same names; docs/numerics.md).
#: MipNeRF's sigmoid clamp in EG3D's OSGDecoder: ``feat = sigmoid(o) * (1 + 2 m) - m``.
SIGMOID_MARGIN = 0.001
#: Activation bias of the density in MipRayMarcher2: ``sigma = softplus(sigma_raw - 1)``.
DENSITY_SHIFT = 1.0
#: Added to the transmittance factor ``1 - alpha`` (MipRayMarcher2's exclusive cumprod).
TRANSMITTANCE_EPS = 1e-10
#: Added to the smoothed coarse weights before they become the importance pdf.
PDF_WEIGHT_FLOOR = 0.01
#: EG3D ``sample_pdf``'s eps: added to each weight, and the smallest cdf step divided by.
PDF_EPS = 1e-5
