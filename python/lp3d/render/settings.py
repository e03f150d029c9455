"""Rendering settings: the one Python definition.

Field names follow EG3D's ``rendering_kwargs`` and are the same in the Rust
``RenderSettings`` struct, the WGSL ``Params`` uniform and the ``.npz`` keys
(``ray_start``, ``ray_end``, ``box_warp`` live in the triplane file because
they belong to the scene; the rest are per render). A cross-language test
checks the defaults against ``lp3d_render.render``'s signature.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Largest ray grid side accepted by every renderer.
MAX_RESOLUTION = 1024
#: Largest coarse or fine sample count per ray (private arrays in the kernel).
MAX_SAMPLES = 256
#: Channels of an EG3D triplane plane / decoder input.
N_CHANNELS = 32
#: Decoder hidden width and output width (density + 32 features).
HIDDEN = 64
N_OUT = 33


@dataclass(frozen=True)
class RenderSettings:
    """How to render (not what): sample counts, resolution and sampling mode.

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
    #: Skips (0 = exact EG3D semantics): early ray termination below this transmittance ...
    transmittance_threshold: float = 0.0
    #: ... and no importance pass for rays whose coarse opacity is below this.
    empty_threshold: float = 0.0
    #: Occupancy grid skip (docs/occupancy.md): intervals between two samples in empty cells of the
    #: triplane's grid have opacity <= this and are taken as 0 without decoding. 0 = off.
    occupancy_epsilon: float = 0.0
    #: ... in the coarse pass too (faster; moves the importance samples, error measured not bounded).
    occupancy_coarse: bool = False

    def validate(self) -> None:
        if not isinstance(self.resolution, int) or not 1 <= self.resolution <= MAX_RESOLUTION:
            raise ValueError(f"resolution must be an int in [1, {MAX_RESOLUTION}], got {self.resolution!r}")
        s, n = self.depth_resolution, self.depth_resolution_importance
        min_s = 4 if n > 0 else 2
        if not isinstance(s, int) or not min_s <= s <= MAX_SAMPLES:
            raise ValueError(
                f"depth_resolution must be an int in [{min_s}, {MAX_SAMPLES}] "
                f"(importance sampling needs at least 4), got {s!r}"
            )
        if not isinstance(n, int) or not (n == 0 or 2 <= n <= MAX_SAMPLES):
            raise ValueError(
                "depth_resolution_importance must be 0 (no importance pass) or an int in "
                f"[2, {MAX_SAMPLES}], got {n!r}"
            )
        for name in ("transmittance_threshold", "empty_threshold", "occupancy_epsilon"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {value!r}")
        if self.occupancy_coarse and self.occupancy_epsilon == 0.0:
            raise ValueError("occupancy_coarse needs occupancy_epsilon > 0")
        if not isinstance(self.seed, int) or not 0 <= self.seed < 2**32:
            raise ValueError(f"seed must be an int in [0, 2**32), got {self.seed!r}")


#: EG3D FFHQ scene defaults (stored per triplane file; ``lp3d_render.DEFAULT_*`` agree, a test checks).
DEFAULT_BOX_WARP = 1.0
DEFAULT_RAY_START = 2.25
DEFAULT_RAY_END = 3.3

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
