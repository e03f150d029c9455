"""Building blocks of the procedural heads' 2-D fields: smoothsteps and logits, a part's four fields
(:class:`PartFields`), the shared noise textures and the hairstyles' shape parameters.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


# --------------------------------------------------------------------------------------- helpers
def smoothstep(e0: float | np.ndarray, e1: float | np.ndarray, v: np.ndarray) -> np.ndarray:
    """Hermite smoothstep from 0 at ``e0`` to 1 at ``e1`` (either order)."""
    t = np.clip((v - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def colour_logits(rgb: Sequence[float]) -> np.ndarray:
    """Colour logits (3, 1, 1) float32: the decoder's sigmoid gives ``rgb`` back (clamped to 2..98%)."""
    c = np.clip(np.asarray(rgb, dtype=np.float64), 0.02, 0.98)
    return np.log(c / (1.0 - c)).astype(np.float32).reshape(3, 1, 1)


def gauss(u: np.ndarray) -> np.ndarray:
    """exp(-u^2). Gaussian bumps are written as products of 1-D factors (one over x, one over y),
    which costs an outer product instead of an exp over the whole grid."""
    return np.exp(-u * u)


def tint(r: float, g: float, b: float) -> np.ndarray:
    """A per-channel logit offset (3, 1, 1) float32."""
    return np.array([r, g, b], dtype=np.float32).reshape(3, 1, 1)


@dataclass(frozen=True)
class PartFields:
    """One part's fields: shape ``A(x, y)``, ``B(x, z)`` (inside where A + B < 1) and colour logits
    ``fc`` over (y, x) and ``gc`` over (z, x); all broadcastable to (R, R) or (3, R, R). With a
    ``window`` (row and column slices of plane 0), ``A`` and ``fc`` cover only that window: the part
    is absent outside it (small parts need not be computed over the whole plane)."""

    A: np.ndarray | float
    B: np.ndarray | float
    fc: np.ndarray | float
    gc: np.ndarray | float
    window: tuple[slice, slice] | None = None


#: A = B = this gives f = g = -1, at or below every version's field floor: an absent part.
EMPTY_FIELD = 4.0
ABSENT_PART = PartFields(EMPTY_FIELD, EMPTY_FIELD, 0.0, 0.0)


class Textures:
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
        self.dots = smoothstep(
            0.75,
            0.95,
            np.sin(x * 520.0 + 2.0 * np.sin(v * 170.0)) * np.sin(v * 470.0 + 1.7 * np.sin(x * 210.0)),
        )
        self.stubble = np.sin(x * 900.0 + 3.0 * np.sin(v * 400.0)) * np.sin(
            v * 800.0 + 2.0 * np.sin(x * 500.0)
        )


@dataclass(frozen=True)
class HairstyleShape:
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


#: Each hairstyle's shape (:data:`~lp3d.teachers.procedural_identity.HAIRSTYLES` names them).
HAIRSTYLE_SHAPES: dict[str, HairstyleShape] = {
    # Bald: a thin skin-coloured scalp over everything but the face, so the face paint (which
    # projects through the head along z) never shows on the back of the head.
    "bald": HairstyleShape(
        0.014, nape=-0.8, hairline=0.85, temple_drop=0.0, curtain_to=-0.8, curtain_from=0.9,
        ears_visible=False,
    ),
    "short": HairstyleShape(0.018, nape=-0.72, hairline=0.62, temple_drop=0.45),
    "long": HairstyleShape(
        0.024, nape=-1.0, hairline=0.64, temple_drop=0.35, curtain_to=-1.4, curtain_from=0.92,
        hang=0.12, flare=0.25, ears_visible=False, parting=True,
    ),
    "bob": HairstyleShape(
        0.03, nape=-0.9, hairline=0.32, temple_drop=0.3, curtain_to=-0.85, curtain_from=0.88,
        hang=0.0, flare=0.08, ears_visible=False,
    ),
    "bun": HairstyleShape(0.015, nape=-0.7, hairline=0.64, temple_drop=0.4, bun=True, parting=True),
    "afro": HairstyleShape(
        0.07, nape=-1.2, hairline=0.55, temple_drop=0.3, curtain_to=-0.45, curtain_from=0.86,
        ears_visible=False, curly=True, round=True,
    ),
}  # fmt: skip
