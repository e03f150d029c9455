"""The procedural teacher: stylised 3D heads written straight into EG3D-format triplanes.

No weights and no training: every identity is a handful of closed-form 2-D fields, and one fixed,
hand-built decoder turns them into density and colour. The construction rests on EG3D's plane quirk
(``docs/eg3d-rendering.md`` §2; :data:`lp3d.render.triplane.PLANE_AXES`):

* Plane 0 samples (x, y), planes 1 and 2 sample (x, z) and (z, x). With plane 2 the transpose of
  plane 1, a channel's triplane value (the *mean* of the three planes) is exactly
  ``(f(x, y) + g(x, z)) / 3``, where plane 0 holds ``f`` and planes 1 and 2 hold ``g / 2`` each.
* Each part owns one **shape channel**: the part is the region ``A(x, y) + B(x, z) < 1``, with ``A``
  acting as a soft front-view mask and ``B`` as a soft top-view mask (an ellipsoid is
  ``A = x^2/a^2 + y^2/b^2``, ``B = z^2/c^2``). Stored as ``f = 1 - A/2`` and ``g = 1 - B/2``, the
  channel mean is ``(2 - (A + B)/2) / 3``: above 1/2 exactly inside. Outside the box EG3D does not
  mask and some planes read zero; each plane's term alone is below 3/2 (``A, B > -1``), so the mean
  there stays below 1/2 and every part is empty beyond the box.
* Each part also owns three **colour channels** holding colour logits ``fc(x, y) + gc(x, z)``:
  ``fc`` paints what is seen from the front (brows, lips, irises, freckles, hair strands, the
  backdrop pattern), ``gc`` what varies with depth (shading, strands seen from the side). Light is
  baked in; the decoder has no view dependence.

8 parts x (1 shape + 3 colour channels) = 32 channels. The decoder (:func:`procedural_decoder`) has one
softplus density unit per part and, per part and colour, a gate pair
``softplus(3 c + beta (o + m)) - softplus(beta (o + m))`` equal to the logit ``3 c`` inside the part
(``o`` = shape mean - 1/2 > -m) and to 0 elsewhere: 8 + 8 x 3 x 2 = 56 of the 64 hidden units.
Output features 3..31 are the part occupancies and per-part colours, so they carry meaning too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lp3d.render.settings import (
    DEFAULT_BOX_WARP,
    DEFAULT_RAY_END,
    DEFAULT_RAY_START,
    HIDDEN,
    N_CHANNELS,
    N_OUT,
)
from lp3d.render.triplane import TriplaneData

Hairstyle = Literal["bald", "short", "long", "bob", "bun", "afro"]
Pattern = Literal["plain", "gradient", "stripes", "checker", "dots", "waves"]
RGB = tuple[float, float, float]

HAIRSTYLES: tuple[Hairstyle, ...] = ("bald", "short", "long", "bob", "bun", "afro")
PATTERNS: tuple[Pattern, ...] = ("plain", "gradient", "stripes", "checker", "dots", "waves")

#: Parts, in shape-channel order; part p's colour logits are channels 8 + 3p .. 8 + 3p + 2. The nose,
#: lips, chin and eye sockets are relief on the head (one surface, so no seams between them).
PARTS: tuple[str, ...] = ("head", "hair", "eyes", "ears", "torso", "background", "glasses", "beard")
HEAD, HAIR, EYES, EARS, TORSO, BACKGROUND, GLASSES, BEARD = range(len(PARTS))
N_PARTS = len(PARTS)

#: Plane resolution of the emitted triplanes (EG3D FFHQ: 256).
RESOLUTION = 256

# ------------------------------------------------------------------------------- decoder constants
#: Shape-channel mean above which a point is inside a part (f alone or g alone stays below it).
INSIDE_MEAN = 0.5
#: Clamps of f and g. The floor bounds far-away values (any floor < 1/2 leaves the shapes unchanged);
#: the ceiling (above 1 for the nose, which has A < 0) keeps each plane's term alone below the
#: inside threshold: ceiling / 3 < INSIDE_MEAN.
FIELD_FLOOR = -1.0
FIELD_CEILING = 1.4
#: Density unit softplus(DENSITY_SLOPE * o); raw density = DENSITY_WEIGHT * sum of units + DENSITY_BIAS.
#: Steep, so surfaces are opaque within a few millimetres and empty space is empty (sigma ~ 1e-3).
DENSITY_SLOPE = 1000.0
DENSITY_WEIGHT = 50.0
DENSITY_BIAS = -6.0
#: Colour gates: logit = COLOUR_GAIN * channel mean, open where o > -GATE_MARGIN, over ~2/GATE_SLOPE.
#: The margin keeps the gate open at the samples just outside a surface that the marcher averages in.
COLOUR_GAIN = 3.0
GATE_SLOPE = 4000.0
GATE_MARGIN = 0.005
#: Occupancy features: sigmoid(OCC_WEIGHT * density unit + OCC_BIAS).
OCC_WEIGHT = 2.0
OCC_BIAS = -4.0
#: Parts whose gated colours are output features 11..31 (7 parts x 3; the beard's is the hair's).
COLOUR_FEATURE_PARTS = (HEAD, HAIR, EYES, EARS, TORSO, BACKGROUND, GLASSES)


def procedural_decoder() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The fixed effective decoder ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` float32.

    Hidden units: 0..7 density units ``softplus(s (mean_p - 1/2))``; unit 8 + 6p + 2k and the one after
    it are part p's gate pair for colour k; 56..63 unused (zero). Outputs: 0 raw density; 1..3 RGB
    (the sum over parts of gated logits); 4..11 (features 3..10) part occupancies; 12..32 (features
    11..31) the gated colours of :data:`COLOUR_FEATURE_PARTS`.
    """
    w0 = np.zeros((HIDDEN, N_CHANNELS))
    b0 = np.zeros(HIDDEN)
    w1 = np.zeros((N_OUT, HIDDEN))
    b1 = np.zeros(N_OUT)
    for p in range(N_PARTS):
        w0[p, p] = DENSITY_SLOPE
        b0[p] = -DENSITY_SLOPE * INSIDE_MEAN
        w1[0, p] = DENSITY_WEIGHT
        w1[4 + p, p] = OCC_WEIGHT
        b1[4 + p] = OCC_BIAS
        for k in range(3):
            on, off = 8 + 6 * p + 2 * k, 9 + 6 * p + 2 * k
            w0[on, N_PARTS + 3 * p + k] = COLOUR_GAIN
            w0[on, p] = w0[off, p] = GATE_SLOPE
            b0[on] = b0[off] = GATE_SLOPE * (GATE_MARGIN - INSIDE_MEAN)
            w1[1 + k, on], w1[1 + k, off] = 1.0, -1.0
            if p in COLOUR_FEATURE_PARTS:
                row = 12 + 3 * COLOUR_FEATURE_PARTS.index(p) + k
                w1[row, on], w1[row, off] = 1.0, -1.0
    b1[0] = DENSITY_BIAS
    w0, b0, w1, b1 = (a.astype(np.float32) for a in (w0, b0, w1, b1))
    return w0, b0, w1, b1


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


# --------------------------------------------------------------------------------------- helpers
def _ss(e0: float | np.ndarray, e1: float | np.ndarray, v: np.ndarray) -> np.ndarray:
    """Hermite smoothstep from 0 at ``e0`` to 1 at ``e1`` (either order)."""
    t = np.clip((v - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _logit(rgb: Sequence[float]) -> np.ndarray:
    """Colour logits (3, 1, 1) float32: the decoder's sigmoid gives ``rgb`` back (clamped to 2..98%)."""
    c = np.clip(np.asarray(rgb, dtype=np.float64), 0.02, 0.98)
    return np.log(c / (1.0 - c)).astype(np.float32).reshape(3, 1, 1)


def _gauss(u: np.ndarray) -> np.ndarray:
    """exp(-u^2). Gaussian bumps are written as products of 1-D factors (one over x, one over y),
    which costs an outer product instead of an exp over the whole grid."""
    return np.exp(-u * u)


def _tint(r: float, g: float, b: float) -> np.ndarray:
    """A per-channel logit offset (3, 1, 1) float32."""
    return np.array([r, g, b], dtype=np.float32).reshape(3, 1, 1)


@dataclass(frozen=True)
class _Part:
    """One part's fields: shape ``A(x, y)``, ``B(x, z)`` (inside where A + B < 1) and colour logits
    ``fc`` over (y, x) and ``gc`` over (z, x); all broadcastable to (R, R) or (3, R, R). With a
    ``window`` (row and column slices of plane 0), ``A`` and ``fc`` cover only that window: the part
    is absent outside it (small parts need not be computed over the whole plane)."""

    A: np.ndarray | float
    B: np.ndarray | float
    fc: np.ndarray | float
    gc: np.ndarray | float
    window: tuple[slice, slice] | None = None


#: A = B = this gives f = g = FIELD_FLOOR: an absent part.
_EMPTY = 2.0 * (1.0 - FIELD_FLOOR)
_ABSENT = _Part(_EMPTY, _EMPTY, 0.0, 0.0)


class _Textures:
    """Seed-independent texture maps over the plane grid (R, R), made once per teacher: hair strands
    and curls seen from the front (x, y) and from above (x, z), freckle dots, beard stubble."""

    def __init__(self, c: np.ndarray) -> None:
        x, v = c[None, :], c[:, None]  # v is y on plane 0, z on planes 1 and 2
        two_pi = 2.0 * np.pi
        self.strands = np.sin(two_pi * (x * 37.0 + 0.6 * np.sin(v * 23.0))) + 0.5 * np.sin(
            two_pi * (x * 91.0 + v * 5.0)
        )
        self.strands_xz = 0.12 * np.sin(two_pi * (v * 41.0 + 0.5 * np.sin(x * 30.0)))
        self.curls = (
            1.6 * np.sin(x * 150.0 + 2.0 * np.sin(v * 110.0)) * np.sin(v * 140.0 + 2.0 * np.sin(x * 100.0))
        )
        self.curls_xz = 0.5 * np.sin(v * 140.0 + 2.0 * np.sin(x * 90.0)) * np.sin(x * 130.0)
        self.dots = _ss(
            0.75,
            0.95,
            np.sin(x * 520.0 + 2.0 * np.sin(v * 170.0)) * np.sin(v * 470.0 + 1.7 * np.sin(x * 210.0)),
        )
        self.stubble = np.sin(x * 900.0 + 3.0 * np.sin(v * 400.0)) * np.sin(
            v * 800.0 + 2.0 * np.sin(x * 500.0)
        )


@dataclass(frozen=True)
class _HairStyle:
    """Shape of a hairstyle, in head units t (0 at the head centre, 1 at the crown, -1 at the chin)."""

    thickness: float  #: over the skull, world units (scaled by hair_length)
    nape: float  #: lowest t at the back
    hairline: float  #: forehead hairline t at the centre
    temple_drop: float  #: how much lower the hairline is at the temples
    curtain_to: float | None = None  #: side curtains beside the face down to this t
    curtain_from: float = 0.9  #: curtains start at this fraction of the face half-width
    hang: float | None = None  #: length below the chin (world units at hair_length 0.5)
    flare: float = 0.0  #: widening of the hanging part per unit of drop
    ears_visible: bool = True
    bun: bool = False
    curly: bool = False
    parting: bool = False
    round: bool = False  #: silhouette an ellipse all round (afro), not the grown skull


_HAIR_STYLES: dict[str, _HairStyle] = {
    # Bald: a thin skin-coloured scalp over everything but the face, so the face paint (which
    # projects through the head along z) never shows on the back of the head.
    "bald": _HairStyle(
        0.014, nape=-0.8, hairline=0.85, temple_drop=0.0, curtain_to=-0.8, curtain_from=0.9,
        ears_visible=False,
    ),
    "short": _HairStyle(0.018, nape=-0.72, hairline=0.62, temple_drop=0.45),
    "long": _HairStyle(
        0.024, nape=-1.0, hairline=0.64, temple_drop=0.35, curtain_to=-1.4, curtain_from=0.92,
        hang=0.12, flare=0.25, ears_visible=False, parting=True,
    ),
    "bob": _HairStyle(
        0.03, nape=-0.9, hairline=0.32, temple_drop=0.3, curtain_to=-0.85, curtain_from=0.88,
        hang=0.0, flare=0.08, ears_visible=False,
    ),
    "bun": _HairStyle(0.015, nape=-0.7, hairline=0.64, temple_drop=0.4, bun=True, parting=True),
    "afro": _HairStyle(
        0.07, nape=-1.2, hairline=0.55, temple_drop=0.3, curtain_to=-0.45, curtain_from=0.86,
        ears_visible=False, curly=True, round=True,
    ),
}  # fmt: skip


# ---------------------------------------------------------------------------------------- teacher
class ProceduralTeacher:
    """Stylised heads as EG3D triplanes, built in closed form: the embedded default teacher.

    ``sample(seed)`` draws :class:`HeadParams` from the seed and builds the triplane with :meth:`build`
    (about 10-15 ms on a 2-core CPU). Coordinate grids, textures and the decoder are made once per
    teacher.
    """

    def __init__(self, resolution: int = RESOLUTION) -> None:
        if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 16:
            raise ValueError(f"resolution must be an int >= 16, got {resolution!r}")
        self.resolution = resolution
        self.box_warp = DEFAULT_BOX_WARP
        # Texel centres in world units (grid_sample with align_corners=False).
        c = ((2.0 * np.arange(resolution) + 1.0) / resolution - 1.0) * (self.box_warp / 2.0)
        self._coords = c.astype(np.float32)
        self._textures = _Textures(self._coords)
        self._decoder = procedural_decoder()

    def decoder(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The fixed decoder shared by every identity (copies): w0 (64, 32), b0 (64,), w1 (33, 64),
        b1 (33,)."""
        w0, b0, w1, b1 = (a.copy() for a in self._decoder)
        return w0, b0, w1, b1

    def sample(self, seed: int) -> TriplaneData:
        """Triplane (3, 32, R, R) float32 of identity ``seed``; ``source`` is ``"procedural seed N"``."""
        return self.build(HeadParams.sample(seed), source=f"procedural seed {int(seed)}")

    def sample_batch(self, seeds: Sequence[int]) -> list[TriplaneData]:
        """``[sample(s) for s in seeds]``."""
        return [self.sample(s) for s in seeds]

    def build(self, params: HeadParams, *, source: str | None = None) -> TriplaneData:
        """The triplane of an explicit identity."""
        parts = _Builder(params, self._coords, self._textures).parts()
        R = self.resolution
        planes = np.empty((3, N_CHANNELS, R, R), dtype=np.float32)
        for p, part in enumerate(parts):
            # f = 1 - A/2 and g = 1 - B/2: the shape channel's mean is (f + g) / 3 (planes 1 and 2 hold
            # g/2 each), and the colour logit COLOUR_GAIN * mean is fc + gc.
            colours = slice(N_PARTS + 3 * p, N_PARTS + 3 * p + 3)
            f, fc = planes[0, p], planes[0, colours]
            if part.window is None:
                np.multiply(part.A, -0.5, out=f)
                f += 1.0
                np.clip(f, FIELD_FLOOR, FIELD_CEILING, out=f)
                fc[...] = part.fc
            else:
                rows, cols = part.window
                f[...] = FIELD_FLOOR
                f[rows, cols] = np.clip(1.0 - 0.5 * np.asarray(part.A), FIELD_FLOOR, FIELD_CEILING)
                fc[...] = 0.0
                fc[:, rows, cols] = part.fc
            # Plane 2 samples (z, x): it gets the transposes. Fields that vary along one axis only are
            # stored as (R, 1) or (1, R), so most transposes are cheap broadcasts.
            g = np.clip(
                0.5 - 0.25 * np.asarray(part.B, dtype=np.float32), 0.5 * FIELD_FLOOR, 0.5 * FIELD_CEILING
            )
            gc = 0.5 * np.asarray(part.gc, dtype=np.float32)
            planes[1, p] = g
            planes[2, p] = g.T
            planes[1, colours] = gc
            planes[2, colours] = np.swapaxes(gc, -1, -2) if gc.ndim >= 2 else gc
        # Copies: TriplaneData keeps the arrays it is given, and a caller may modify its triplane.
        w0, b0, w1, b1 = self.decoder()
        return TriplaneData(
            planes=planes,
            w0=w0,
            b0=b0,
            w1=w1,
            b1=b1,
            box_warp=self.box_warp,
            ray_start=DEFAULT_RAY_START,
            ray_end=DEFAULT_RAY_END,
            source=source,
        )


class _Builder:
    """The eight parts of one identity, from the texel centres ``coords`` (R,): ``x`` (1, R) indexes
    columns; ``y`` = ``z`` (R, 1) index rows, read as y in the (x, y) fields (A, fc) and as z in the
    (x, z) fields (B, gc)."""

    def __init__(self, p: HeadParams, coords: np.ndarray, textures: _Textures) -> None:
        self.p = p
        self.coords = coords
        self.tex = textures
        self.x = coords[None, :]
        self.y = self.z = coords[:, None]
        self.ax = np.abs(self.x)
        self.yc = 0.03  # head centre height
        self.zc = 0.02  # head centre depth (EG3D's FFHQ cameras look at z = 0.2, about the face)
        self.ey = self.yc + 0.012  # eye height
        self.skin = _logit(p.skin_rgb)
        self.hair_logit = _logit(p.hair_rgb)
        self.hair_lightness = float(np.mean(p.hair_rgb))

    def window(self, x0: float, x1: float, y0: float, y1: float) -> tuple[slice, slice]:
        """Row and column slices of the texels with y0 <= y <= y1 and x0 <= x <= x1."""
        c = self.coords
        rows = slice(int(np.searchsorted(c, y0)), int(np.searchsorted(c, y1, side="right")))
        cols = slice(int(np.searchsorted(c, x0)), int(np.searchsorted(c, x1, side="right")))
        return rows, cols

    def parts(self) -> list[_Part]:
        p = self.p
        return [
            self.head(),
            self.hair(),
            self.eyes(),
            self.ears(),
            self.torso(),
            self.background(),
            self.glasses() if p.glasses else _ABSENT,
            self.beard() if p.beard else _ABSENT,
        ]

    # -- head -------------------------------------------------------------------------------------
    @property
    def nose_tip_y(self) -> float:
        return self.ey - 0.30 * self.p.head_height * (0.85 + 0.15 * self.p.nose_size)

    @property
    def mouth_y(self) -> float:
        return self.yc - 0.58 * self.p.head_height

    def head_width(self, y: np.ndarray | float) -> np.ndarray | float:
        """Half-width of the skull ellipse at height y (narrower toward the jaw)."""
        p = self.p
        t = (y - self.yc) / p.head_height
        return p.head_width * (1.0 - (1.0 - p.jaw_width) * _ss(0.15, -1.0, t))

    def skull_A(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        """Front-view field of the plain skull: ``(x / width(y))^2 + t^2``."""
        t = (y - self.yc) / self.p.head_height
        return (x / self.head_width(y)) ** 2 + t * t

    def relief(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Face relief (world units toward +z) over (x, y): nose, sockets, brow ridge, lips, chin."""
        p = self.p
        ax = np.abs(x)
        re = p.eye_size
        ns = p.nose_size
        # Nose: a ridge from the brow to the tip, wider and higher toward the tip, with wings.
        y_tip = self.nose_tip_y
        y_top = self.ey + 0.008
        along = np.clip((y - y_tip) / (y_top - y_tip), 0.0, 1.0)  # 0 at the tip, 1 at the bridge top
        height = 0.032 * ns * (0.25 + 0.75 * (1.0 - along) ** 1.4) * _ss(y_top + 0.005, y_top - 0.02, y)
        under = _ss(y_tip - 0.017 * ns, y_tip, y)  # the underside turns back to the lip
        width = 0.007 + 0.011 * ns * (1.0 - along) ** 1.5
        across = np.cos(np.clip(x / width, -1.0, 1.0) * (np.pi / 2)) ** 2
        r = height * under * across
        wings = np.exp(-(((ax - 0.75 * width) / (0.55 * width)) ** 2)) * _gauss(
            (y - y_tip + 0.008 * ns) / 0.008
        )
        r = r + 0.012 * ns * wings
        # Eye sockets (the eyeballs show through an almond-shaped opening), brow ridge, cheekbones.
        dx = ax - p.eye_spacing
        r = r - 0.011 * _gauss(dx / (1.3 * re)) * _gauss((y - self.ey) / (0.55 * re))
        r = r + 0.005 * _gauss(dx / 0.035) * _gauss((y - self.ey - 1.9 * re) / 0.010)
        r = r + 0.005 * _gauss((ax - 0.07) / 0.03) * _gauss((y - self.ey + 0.04) / 0.02)
        # Lips: two rolls either side of the mouth line, and the chin.
        ym, lf = self.mouth_y, p.lip_fullness
        r = r + 0.007 * lf * np.exp(-((x / (0.026 * lf)) ** 4)) * _gauss((y - ym - 0.005 * lf) / (0.005 * lf))
        r = r + 0.008 * lf * np.exp(-((x / (0.024 * lf)) ** 4)) * _gauss((y - ym + 0.006 * lf) / (0.006 * lf))
        r = r - 0.004 * _gauss(x / 0.025) * _gauss((y - ym) / 0.002)
        r = r + 0.01 * _gauss(x / 0.03) * _gauss((y - self.yc + 0.86 * p.head_height) / 0.02)
        return r

    def head_A(self, x: np.ndarray, y: np.ndarray, A0: np.ndarray) -> np.ndarray:
        """Front-view field of the head with the face relief, from the plain skull's ``A0`` at (x, y):
        the face's surface is the height field ``zc + D (sqrt(1 - A0) + relief / D)``, so
        ``A = 1 - (sqrt(1 - A0) + relief / D)^2``. A goes below 0 on the nose (down to about -0.5),
        within FIELD_CEILING, so plane 0 alone still decodes as empty."""
        q = np.sqrt(np.maximum(0.0, 1.0 - A0)) + self.relief(x, y) / self.p.head_depth
        return np.where(A0 < 1.0, 1.0 - np.maximum(q, 0.0) ** 2, A0)

    def head_B(self, z: np.ndarray) -> np.ndarray:
        # Steep behind the centre (power 6): the face relief barely moves the back of the skull.
        dz = z - self.zc
        D = self.p.head_depth
        return np.where(dz > 0, (dz / D) ** 2, (dz / (1.03 * D)) ** 6)

    def face_z(self, x: float, y: float) -> float:
        """Depth of the plain skull's front surface at (x, y) (no relief)."""
        a = float(self.skull_A(x, y))
        return self.zc + self.p.head_depth * math.sqrt(max(0.0, 1.0 - a))

    def face_window(self) -> tuple[slice, slice]:
        """Where the face relief and paint live (they are negligible outside it)."""
        p = self.p
        return self.window(-0.13, 0.13, self.yc - p.head_height - 0.03, self.ey + 0.075)

    def head(self) -> _Part:
        """The skull ellipsoid (narrowing to the jaw) with the face as relief, painted."""
        p, x, y, z = self.p, self.x, self.y, self.z
        A = self.skull_A(x, y)
        # Skin lit from one side and from above, over (x, y); over (x, z) the front is lit and the sides
        # and back fall off.
        fc = self.skin + (0.25 * p.light_x * x / p.head_width + 0.9 * (y - self.yc)).astype(np.float32)
        gc = (0.8 * (z - self.zc) / p.head_depth - 0.2).astype(np.float32)
        rows, cols = self.face_window()
        xw, yw = x[:, cols], y[rows, :]
        A[rows, cols] = self.head_A(xw, yw, A[rows, cols])
        fc[:, rows, cols] = self.face_paint(xw, yw, fc[:, rows, cols])
        return _Part(A, self.head_B(z), fc, gc)

    def face_paint(self, x: np.ndarray, y: np.ndarray, fc: np.ndarray) -> np.ndarray:
        """The face painted over the lit skin ``fc`` (3, h, w) at (x (1, w), y (h, 1))."""
        p = self.p
        ax = np.abs(x)
        re = p.eye_size
        dx = ax - p.eye_spacing
        ym = self.mouth_y
        fc = fc.copy()
        brow_y = self.ey + 1.75 * re + 0.006 * (1.0 - (dx / 0.028) ** 2)
        brow = np.exp(-(((y - brow_y) / (0.0042 * p.brow_thickness)) ** 2)) * _ss(
            0.032, 0.024, np.abs(dx + 0.002)
        )
        fc += brow * (_logit(np.asarray(p.hair_rgb) * 0.6 + 0.04) - fc)
        # Upper lash line along the top of the eye opening.
        lid_y = self.ey + 0.62 * re * np.sqrt(np.maximum(0.0, 1.0 - (dx / (1.05 * re)) ** 2))
        liner = np.exp(-(((y - lid_y) / 0.0026) ** 2)) * _ss(1.15 * re, 0.8 * re, np.abs(dx))
        fc += liner * (_logit((0.08, 0.05, 0.05)) - fc)
        lf = p.lip_fullness
        lips = _ss(1.0, 0.75, (x / (0.027 * lf)) ** 2 + ((y - ym + 0.001) / (0.0115 * lf)) ** 2)
        fc += lips * (_logit(p.lip_rgb) - fc)
        fc -= 1.2 * _gauss(x / (0.025 * lf)) * _gauss((y - ym) / 0.0018)
        # Painted shading where the relief is too small to shade itself: the lid crease, the side of the
        # nose away from the light, under the nose and the lower lip; light on the nose ridge; nostrils.
        crease = _gauss((y - self.ey - 0.95 * re) / 0.0035) * _ss(1.3 * re, 0.7 * re, np.abs(dx))
        y_tip = self.nose_tip_y
        h_up = self.ey + 0.012 - y_tip
        ns = p.nose_size
        side = -1.0 if p.light_x >= 0 else 1.0
        nose_side = _gauss((x - side * 0.014 * ns) / 0.008) * _gauss((y - y_tip - 0.4 * h_up) / (0.5 * h_up))
        under_nose = _gauss(x / 0.014) * _gauss((y - y_tip + 0.02 * ns) / 0.005)
        nostrils = _gauss((ax - 0.008 * ns) / 0.0045) * _gauss((y - y_tip + 0.012 * ns) / 0.0035)
        under_lip = _gauss(x / 0.02) * _gauss((y - ym + 0.02) / 0.005)
        ridge = _gauss(x / 0.004) * (_ss(self.ey, y_tip, y) * _ss(y_tip - 0.012, y_tip, y))
        fc -= (
            0.5 * crease
            + (0.3 + 0.3 * abs(p.light_x)) * nose_side
            + 0.5 * under_nose
            + 1.4 * nostrils
            + 0.35 * under_lip
            - 0.35 * ridge
        )
        blush = _gauss((ax - 0.072) / 0.028) * _gauss((y - self.ey + 0.052) / 0.025)
        fc += 0.35 * blush * _tint(0.6, -0.4, -0.3)
        if p.freckles > 0:
            area = _gauss((ax - 0.05) / 0.04) * _gauss((y - self.ey + 0.04) / 0.03)
            fc -= 0.9 * p.freckles * area * self.tex.dots[self.face_window()] * _tint(0.6, 0.9, 1.1)
        return fc

    # -- eyes -------------------------------------------------------------------------------------
    def eyes(self) -> _Part:
        """Two spheres (x enters A through |x|), set deep so only the almond opening shows."""
        p, z = self.p, self.z
        re, ex, ey = p.eye_size, p.eye_spacing, self.ey
        ez = self.face_z(ex, ey) - 0.88 * re
        reach = ex + 2.1 * re  # A >= 4 (f at its floor) beyond 2 radii: nothing to compute there
        rows, cols = self.window(-reach, reach, ey - 2.1 * re, ey + 2.1 * re)
        x, y = self.x[:, cols], self.y[rows, :]
        dx = np.abs(x) - ex
        r2 = (dx * dx + (y - ey) ** 2) / (re * re)
        r = np.sqrt(r2)
        fc = _logit((0.93, 0.91, 0.88)) - 0.6 * _ss(0.6, 0.95, r)  # corners in shadow
        fc = fc + _ss(0.56, 0.5, r) * (_logit(p.eye_rgb) - fc)
        fc = fc - 0.8 * _ss(0.3, 0.5, r) * _ss(0.56, 0.5, r)  # darker iris rim
        fc = fc + _ss(0.24, 0.2, r) * (_logit((0.02, 0.02, 0.02)) - fc)
        glint = _gauss((dx + 0.2 * re * np.sign(x)) / (0.09 * re)) * _gauss((y - ey - 0.2 * re) / (0.09 * re))
        fc = fc + glint * (_logit((0.97, 0.97, 0.97)) - fc)
        return _Part(r2, ((z - ez) / re) ** 2, fc, 0.0, window=(rows, cols))

    # -- ears -------------------------------------------------------------------------------------
    @property
    def ear_back(self) -> float:
        """Depth of the back edge of the ears."""
        return self.zc - 0.03 - 0.024 * self.p.ear_size

    def ears(self) -> _Part:
        """Thin upright discs standing out from the sides of the skull, tilted back a little."""
        p, y, z = self.p, self.y, self.z
        es = p.ear_size
        ey = self.ey - 0.03
        ex = float(self.head_width(ey)) + 0.003
        hy = 0.040 * es
        dz = 0.024 * es
        ez = self.zc - 0.03
        A = ((self.ax - ex) / 0.012) ** 2 + ((y - ey) / hy) ** 2
        B = ((z - ez) / dz) ** 2 - 0.18 * _ss(ex, ex + 0.02, self.ax) * (z - ez) / dz
        inner = np.exp(-(((y - ey) / (0.6 * hy)) ** 2))
        fc = self.skin + (0.15 - 0.5 * inner).astype(np.float32) + _tint(0.15, -0.05, -0.05)
        gc = (-0.6 * np.exp(-(((z - ez) / (0.6 * dz)) ** 2))).astype(np.float32)
        return _Part(A, B, fc.astype(np.float32), gc)

    # -- torso ------------------------------------------------------------------------------------
    def _torso_fields(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Neck widening into shoulders: ``A`` over (x, y), and per column the depth centre and radius."""
        p = self.p
        H = p.head_height
        y_sh = self.yc - H - 0.085  # shoulder line
        wn = 0.48 * p.head_width
        wt = wn + (0.42 - wn) * _ss(y_sh + 0.04, y_sh - 0.12, y)
        y_top = self.yc - 0.45 * H  # the neck ends inside the head
        A = (x / wt) ** 2 + np.where(y > y_top, ((y - y_top) / 0.04) ** 2, 0.0)
        ax = np.abs(x)
        zt = self.zc - 0.05 - 0.02 * _ss(0.05, 0.25, ax)
        dt = 0.062 + 0.075 * _ss(0.04, 0.2, ax)
        return A, zt, dt

    def torso_front(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth of the neck's and shoulders' front surface over (x, y) (zc where there is none)."""
        A, zt, dt = self._torso_fields(x, y)
        return np.where(A < 1.0, zt + dt * np.sqrt(np.maximum(0.0, 1.0 - A)), self.zc)

    def torso(self) -> _Part:
        p, x, y, z = self.p, self.x, self.y, self.z
        H = p.head_height
        A, zt, dt = self._torso_fields(x, y)
        neckline = self.yc - H - 0.105 + 3.0 * x * x
        shirt = _ss(neckline + 0.004, neckline - 0.004, y)
        chin_shadow = _ss(self.yc - 0.7 * H, self.yc - 1.0 * H - 0.03, y)
        neck = self.skin - (0.9 * (1.0 - chin_shadow)).astype(np.float32)
        fc = neck + shirt * (_logit(p.cloth_rgb) - neck) + (p.light_x * x).astype(np.float32)
        gc = (5.0 * (z - self.zc)).astype(np.float32)
        return _Part(A, ((z - zt) / dt) ** 2, fc.astype(np.float32), gc)

    # -- background -------------------------------------------------------------------------------
    def background(self) -> _Part:
        """Outside an elliptic cylinder about the y axis whose front lies beyond the box: a bowl behind
        the head that wraps round the sides, so oblique views still end on a surface."""
        p, x, y, z = self.p, self.x, self.y, self.z
        rho = np.sqrt((x / 0.44) ** 2 + ((z - 0.3) / 0.75) ** 2)
        B = np.maximum(0.0, 1.0 + (1.0 - rho) * 12.0)
        c1 = _logit(p.background_rgb)
        c2 = _logit(np.asarray(p.background_rgb) * (1.0 - p.pattern_contrast))
        k = 2.0 * np.pi * p.pattern_scale
        pattern = p.background_pattern
        if pattern == "plain":
            m = np.full((1, 1), 0.15)
        elif pattern == "gradient":
            m = _ss(-0.4, 0.4, y)
        elif pattern == "stripes":
            m = _ss(-0.3, 0.3, np.sin(k * (x + 0.3 * y)))
        elif pattern == "checker":
            m = _ss(-0.2, 0.2, np.sin(k * x) * np.sin(k * y))
        elif pattern == "dots":
            m = _ss(0.5, 0.7, np.cos(k * x) * np.cos(k * y))
        else:
            m = 0.5 + 0.5 * np.sin(k * y + 3.0 * np.sin(3.0 * np.pi * x))
        fc = c1 + m.astype(np.float32) * (c2 - c1)
        gc = (-1.2 * np.abs(x) + 0.0 * z).astype(np.float32)  # darker toward the sides
        return _Part(0.0, B, fc.astype(np.float32), gc)

    # -- hair -------------------------------------------------------------------------------------
    def hair(self) -> _Part:
        """Hair as a depth interval per front-view pixel.

        With ``B(z) = ((z - zh) / dzf)^2`` in front of ``zh`` and ``((z - zh) / dzb)^2`` behind it, and
        ``A = 1 - s(x, y)^2``, the hair at (x, y) spans ``zh - dzb s < z < zh + dzf s``. ``zh`` sits
        just behind the skull, so any ``s`` in [0, 1] covers the back of the head, while the front
        either lies just in front of the (grown) skull (``s_cover``: crown, forehead, curtains) or well
        behind the face (``s_hidden``). A cover mask picks between the two; a silhouette ends it.
        """
        p, x, y, z = self.p, self.x, self.y, self.z
        W, H, D = p.head_width, p.head_height, p.head_depth
        yc, zc = self.yc, self.zc
        L = p.hair_length
        st = _HAIR_STYLES[p.hairstyle]
        t = (y - yc) / H
        ax = self.ax
        th = st.thickness * (0.75 + 0.5 * L)
        zh = zc - 1.03 * D - 0.012  # just behind the skull: any s >= 0 covers the back of the head
        dzb = 0.35 * D + 0.6 * th
        # Silhouette (front view): the skull outline grown by th (delta > 0 inside), or for the afro an
        # ellipse centred above the head; then a hanging part, the nape and a bun.
        if st.round:
            u, v = x / (W + th), (y - yc - 0.35 * H) / (0.95 * H + th)
            delta = 1.0 - np.sqrt(u * u + v * v)
        else:
            u, v = x / (self.head_width(y) + th), (y - yc) / (H + th)
            delta = 1.0 - np.sqrt(u * u + np.maximum(v, 0.0) ** 2)
        if st.hang is not None:
            hang_w = W + th + st.flare * np.maximum(yc - y, 0.0)
            y_end = yc - H - st.hang * (0.6 + 0.8 * L) - 0.03 * (1.0 - (x / hang_w) ** 2)
            hang = np.minimum(np.minimum(1.0 - ax / hang_w, (y - y_end) / 0.04), (yc - y) / 0.02)
            delta = np.maximum(delta, hang)
        delta = np.minimum(delta, (t - st.nape) * H / 0.03)
        # Round the outline over half the thickness, outside the skull: a wider rounding would pull the
        # front back to zh over the skull, leaving it thinly (or not) covered.
        edge = np.sqrt(np.clip(delta / (0.5 * th / (W + th)), 0.0, 1.0))
        # Reference depths: the front of the skull (or, below the chin, of the neck), and the front of
        # the skull grown by th in every direction (so covering hair is th thick on the sides too).
        q = np.sqrt(np.maximum(0.0, 1.0 - self.skull_A(x, y)))
        neck = self.torso_front(x, y)
        z_front = np.maximum(zc + D * q, neck)
        grown = self.skull_A(x * (W / (W + th)), yc + (y - yc) * (H / (H + th)))
        z_cover = np.maximum(zc + (D + th) * np.sqrt(np.maximum(0.0, 1.0 - grown)), neck + th)
        # Front radius per column: just enough for the deepest cover there. Smaller radii make the field
        # steeper in z, so the colour gate ends closer to the hair's hidden front.
        dzf = np.max(z_cover, axis=0, keepdims=True) + 0.005 - zh
        s_cover = np.clip((z_cover - zh) / dzf, 0.0, 1.0)
        # Hidden fronts stay well behind the face: the field is soft there (small s), so the hair's
        # colour gate reaches a few centimetres past it.
        s_hidden = np.clip((z_front - 0.07 - zh) / dzf, 0.0, 0.4)
        # Cover mask: the forehead above a hairline that drops toward the temples; curtains on the sides.
        ux = ax / W
        t_hl = st.hairline - st.temple_drop * ux * ux
        cover = _ss(t_hl - 0.03, t_hl + 0.02, t)
        if st.curtain_to is not None:
            face_w = np.maximum(self.head_width(y) * np.sqrt(np.maximum(0.0, 1.0 - t * t)), 1e-3)
            curtain = _ss(st.curtain_from, st.curtain_from + 0.08, ax / face_w)
            cover = np.maximum(cover, curtain * _ss(st.curtain_to - 0.15, st.curtain_to, t))
        s = edge * (cover * s_cover + (1.0 - cover) * s_hidden)
        if st.ears_visible:
            # Beside the ears only the back of the head keeps hair: the front there stops just behind
            # the ear (a cap on s, not a factor, so the field stays steep where it crosses the skin).
            ear = _gauss((ax - W) / 0.03) * _gauss((y - self.ey + 0.03) / 0.05)
            s_ear = (self.ear_back - 0.03 - zh) / dzf
            s = s - ear * np.maximum(s - s_ear, 0.0)
        if st.bun:
            rb = 0.042 + 0.02 * L
            yb = yc + H + th + 0.6 * rb
            bun = 1.0 - ((x / rb) ** 2 + ((y - yb) / rb) ** 2)
            s = np.maximum(s, 0.4 * np.sqrt(np.clip(bun, 0.0, 1.0)))
            delta = np.maximum(delta, bun)
        A = 1.0 - s * s + 40.0 * np.maximum(-delta, 0.0)
        B = (np.maximum(z - zh, 0.0) / dzf) ** 2 + (np.maximum(zh - z, 0.0) / dzb) ** 2
        # Colour: strands (or curls) over (x, y) and (x, z), a sheen band on the crown, darker below.
        if p.hairstyle == "bald":
            # A thin scalp of skin, lit as the head.
            fc = self.skin + (0.25 * p.light_x * x / W + 0.9 * (y - yc))
            gc = 0.8 * (z - zc) / D - 0.2
            return _Part(A, B, fc, gc)
        tex, tex_xz = (
            (self.tex.curls, self.tex.curls_xz) if st.curly else (self.tex.strands, self.tex.strands_xz)
        )
        shine = 0.8 * (1.0 - 0.5 * self.hair_lightness) * _gauss((t - 0.75) / 0.12)
        parting = 1.2 * _gauss(x / 0.004) * _ss(0.5, 0.7, t) if st.parting else 0.0
        fc = self.hair_logit + (0.3 * tex + (shine - parting + 1.2 * (y - yc)))
        gc = tex_xz + 0.6 * (z - zc) / D
        return _Part(A, B, fc, gc)

    # -- glasses and beard -------------------------------------------------------------------------
    def glasses(self) -> _Part:
        """Two rims, a bridge and a bar out to the temples in one thin slab in front of the eyes
        (front view: rims and bars; top view: the slab), then arms running back to the ears, bending
        out around the skull (front view: the bars; top view: the arm curves)."""
        p, z = self.p, self.z
        re, ex, ey = p.eye_size, p.eye_spacing, self.ey
        zg = self.face_z(ex, ey) + 0.018
        R = 1.6 * re
        w = 0.0055  # half thickness of the frame wire (thinner wires break up under 48 + 48 samples)
        head_w = float(self.head_width(ey))
        hinge_x, arm_x = 0.92 * head_w, head_w + 0.007
        rows, cols = self.window(-arm_x - 2 * w, arm_x + 2 * w, ey - 1.3 * R, ey + 1.3 * R)
        x, y = self.x[:, cols], self.y[rows, :]
        ax = np.abs(x)
        rims = ((np.sqrt((ax - ex) ** 2 + ((y - ey) * 1.2) ** 2) - R) / w) ** 2
        bar = ((y - ey - 0.35 * re) / w) ** 2
        bridge = np.where(ax < ex - R + 0.002, bar, _EMPTY)
        bars = np.where((ax > ex + R - 0.002) & (ax < arm_x + w), bar, _EMPTY)
        A = np.minimum(np.minimum(rims, bridge), bars)
        front = np.where(self.ax < hinge_x + w, ((z - zg) / w) ** 2, _EMPTY)
        z_ear = self.zc - 0.04
        curve_x = hinge_x + (arm_x - hinge_x) * _ss(zg, zg - 0.07, z)
        arm = ((self.ax - curve_x) / w) ** 2 + (
            np.maximum(z - zg, 0.0) ** 2 + np.maximum(z_ear - z, 0.0) ** 2
        ) / w**2
        B = np.minimum(np.minimum(front, arm), _EMPTY)
        fc = np.broadcast_to(_logit(p.glasses_rgb), (3, *A.shape))
        return _Part(np.minimum(A, _EMPTY), B, fc, 0.0, window=(rows, cols))

    def beard(self) -> _Part:
        """A layer th thick over the jaw, chin and upper lip: the skull grown by th, kept where a
        front-view mask says beard (below a line from the sideburns to the mouth, the mouth left
        open), with a short back radius so the layer never reaches the back of the head."""
        p, z = self.p, self.z
        W, H, D = p.head_width, p.head_height, p.head_depth
        yc, zc, ym = self.yc, self.zc, self.mouth_y
        th = 0.008 + 0.008 * p.hair_length
        rows, cols = self.window(-W - th - 0.01, W + th + 0.01, yc - H - th - 0.06, self.ey)
        x, y = self.x[:, cols], self.y[rows, :]
        grown = self.skull_A(x * (W / (W + th)), yc + (y - yc) * (H / (H + th)))
        line = ym + 0.018 + (self.ey - 0.03 - ym - 0.018) * (np.abs(x) / W) ** 3  # up to the sideburns
        mask = _ss(line + 0.004, line - 0.004, y)
        mouth = _ss(1.0, 0.7, (x / 0.03) ** 2 + ((y - ym) / 0.012) ** 2)
        A = grown + 3.0 * (1.0 - mask * (1.0 - mouth))
        dz = z - zc
        B = np.where(dz > 0, (dz / (D + th)) ** 2, (dz / (0.5 * D)) ** 2)
        fc = self.hair_logit + (0.35 * self.tex.stubble[rows, cols] - 0.2 + 0.25 * p.light_x * x / W)
        gc = (0.6 * dz / D).astype(np.float32)
        return _Part(A, B, fc, gc, window=(rows, cols))
