"""Who a procedural head is: :class:`HeadParams` (skin, hair, eyes, hairstyle, glasses, backdrop ...),
drawn from a seed with the palettes and probabilities below. Plain data, no geometry.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

Hairstyle = Literal["bald", "short", "long", "bob", "bun", "afro"]
Pattern = Literal["plain", "gradient", "stripes", "checker", "dots", "waves"]
RGB = tuple[float, float, float]

HAIRSTYLES: tuple[Hairstyle, ...] = ("bald", "short", "long", "bob", "bun", "afro")
PATTERNS: tuple[Pattern, ...] = ("plain", "gradient", "stripes", "checker", "dots", "waves")


# ------------------------------------------------------------------------------------ identities
_SKIN: tuple[RGB, ...] = (
    (0.96, 0.80, 0.70), (0.93, 0.74, 0.61), (0.87, 0.66, 0.51), (0.78, 0.57, 0.41),
    (0.66, 0.46, 0.32), (0.50, 0.34, 0.23), (0.36, 0.24, 0.16),
)  # fmt: skip
_HAIR: tuple[RGB, ...] = (
    (0.05, 0.045, 0.04), (0.16, 0.10, 0.06), (0.33, 0.20, 0.10), (0.55, 0.25, 0.10),
    (0.86, 0.70, 0.42), (0.92, 0.90, 0.82), (0.55, 0.55, 0.56), (0.18, 0.30, 0.75), (0.85, 0.35, 0.55),
)  # fmt: skip
_HAIR_P = (0.2, 0.2, 0.16, 0.1, 0.12, 0.05, 0.07, 0.05, 0.05)
_EYES: tuple[RGB, ...] = (
    (0.36, 0.20, 0.09), (0.16, 0.09, 0.05), (0.30, 0.52, 0.82), (0.28, 0.56, 0.34),
    (0.52, 0.42, 0.20), (0.50, 0.56, 0.62),
)  # fmt: skip
_LIPS: tuple[RGB, ...] = ((0.78, 0.42, 0.42), (0.72, 0.32, 0.34), (0.80, 0.12, 0.16), (0.45, 0.15, 0.25))
_CLOTH: tuple[RGB, ...] = (
    (0.12, 0.14, 0.20), (0.85, 0.85, 0.85), (0.60, 0.12, 0.12), (0.18, 0.40, 0.22),
    (0.22, 0.30, 0.62), (0.85, 0.65, 0.20), (0.35, 0.35, 0.37), (0.55, 0.35, 0.60),
)  # fmt: skip
_BACKDROP: tuple[RGB, ...] = (
    (0.80, 0.82, 0.85), (0.55, 0.70, 0.85), (0.85, 0.78, 0.62), (0.45, 0.60, 0.45),
    (0.30, 0.32, 0.38), (0.88, 0.62, 0.55), (0.62, 0.55, 0.75), (0.93, 0.90, 0.80),
)  # fmt: skip
_FRAMES: tuple[RGB, ...] = ((0.05, 0.05, 0.05), (0.45, 0.20, 0.08), (0.75, 0.60, 0.25), (0.70, 0.10, 0.12))
_HAIRSTYLE_P = (0.1, 0.26, 0.24, 0.14, 0.12, 0.14)


def _colour(
    rng: np.random.Generator, palette: Sequence[RGB], amount: float, p: Sequence[float] | None = None
) -> RGB:
    """A palette entry (drawn with probabilities ``p``) jittered by up to ``amount`` per channel."""
    base = np.asarray(palette[int(rng.choice(len(palette), p=p))])
    r, g, b = (float(v) for v in np.clip(base + rng.uniform(-amount, amount, 3), 0.02, 0.98))
    return r, g, b


@dataclass(frozen=True)
class HeadParams:
    """The identity of one procedural head (world units: the triplane box is [-0.5, 0.5]^3; the face
    looks toward +z). Colours are RGB in [0, 1]. :meth:`sample` draws every field independently."""

    head_width: float  #: half-width of the skull at the cheekbones
    head_height: float  #: half-height, crown to chin
    head_depth: float  #: half-depth, face to back of the skull
    jaw_width: float  #: width at the jaw as a fraction of head_width
    eye_spacing: float  #: x of each eye centre
    eye_size: float  #: eyeball radius
    nose_size: float  #: scale of the nose (length, width, protrusion)
    ear_size: float  #: scale of the ears
    lip_fullness: float  #: scale of the lips (width, height, relief)
    brow_thickness: float  #: relative thickness of the painted brows
    hairstyle: Hairstyle
    hair_length: float  #: 0..1: how far long hair falls, how thick the rest is
    glasses: bool
    beard: bool
    skin_rgb: RGB
    hair_rgb: RGB
    eye_rgb: RGB
    lip_rgb: RGB
    cloth_rgb: RGB
    glasses_rgb: RGB
    background_rgb: RGB
    background_pattern: Pattern
    pattern_contrast: float  #: 0..1: how much darker the pattern's second colour is
    pattern_scale: float  #: spatial frequency of the backdrop pattern (cycles per unit)
    freckles: float  #: 0..1 amount of freckles
    light_x: float  #: -1..1: the key light's side (+1: from +x)

    @classmethod
    def sample(cls, seed: int) -> HeadParams:
        """Draw an identity from ``seed`` (an int >= 0), deterministically (numpy's PCG64)."""
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        rng = np.random.default_rng([int(seed), 0x1F3D])
        return cls(
            head_width=float(rng.uniform(0.130, 0.155)),
            head_height=float(rng.uniform(0.200, 0.230)),
            head_depth=float(rng.uniform(0.170, 0.195)),
            jaw_width=float(rng.uniform(0.55, 0.85)),
            eye_spacing=float(rng.uniform(0.047, 0.057)),
            eye_size=float(rng.uniform(0.018, 0.022)),
            nose_size=float(rng.uniform(0.8, 1.25)),
            ear_size=float(rng.uniform(0.8, 1.2)),
            lip_fullness=float(rng.uniform(0.8, 1.25)),
            brow_thickness=float(rng.uniform(0.6, 1.5)),
            hairstyle=HAIRSTYLES[int(rng.choice(len(HAIRSTYLES), p=_HAIRSTYLE_P))],
            hair_length=float(rng.uniform(0.0, 1.0)),
            glasses=bool(rng.random() < 0.3),
            beard=bool(rng.random() < 0.2),
            skin_rgb=_colour(rng, _SKIN, 0.03),
            hair_rgb=_colour(rng, _HAIR, 0.04, _HAIR_P),
            eye_rgb=_colour(rng, _EYES, 0.04),
            lip_rgb=_colour(rng, _LIPS, 0.05),
            cloth_rgb=_colour(rng, _CLOTH, 0.06),
            glasses_rgb=_colour(rng, _FRAMES, 0.04),
            background_rgb=_colour(rng, _BACKDROP, 0.06),
            background_pattern=PATTERNS[int(rng.integers(len(PATTERNS)))],
            pattern_contrast=float(rng.uniform(0.2, 0.45)),
            pattern_scale=float(rng.uniform(4.0, 9.0)),
            freckles=float(rng.uniform(0.3, 1.0)) if rng.random() < 0.25 else 0.0,
            light_x=float(rng.uniform(-1.0, 1.0)),
        )
