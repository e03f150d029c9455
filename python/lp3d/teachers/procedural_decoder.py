"""The procedural teacher's channel layout and its hand-built decoders (see
:mod:`lp3d.teachers.procedural` for the construction): the eight parts, each with one shape and three
colour channels, and :func:`procedural_decoder`, whose density and gate units read them.

Two designs (:class:`DecoderDesign`), one per teacher version:

* **v1** (the first shipped model's teacher): sharpness in the decoder. Density and gate units have
  gains of 1,000-4,000 on plane values of order 1, so every unit is a step of the plane values and
  surfaces turn opaque within millimetres: thinner than the 48+48 sampler's spacing (rings), and a
  small plane error flips whole parts.
* **v2** (the default): sharpness in the planes, as EG3D keeps it. Shape channels are stored scaled
  (``shape_scale``) and clamped close to the surfaces (``field_floor``), the decoder's gains are of
  order 1-10, and density rises over about a centimetre below a surface: soft on the sampler's scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lp3d.render.settings import (
    HIDDEN,
    N_CHANNELS,
    N_OUT,
)

#: Parts, in shape-channel order; part p's colour logits are channels 8 + 3p .. 8 + 3p + 2. The nose,
#: lips, chin and eye sockets are relief on the head (one surface, so no seams between them).
PARTS: tuple[str, ...] = ("head", "hair", "eyes", "ears", "torso", "background", "glasses", "beard")
HEAD, HAIR, EYES, EARS, TORSO, BACKGROUND, GLASSES, BEARD = range(len(PARTS))
N_PARTS = len(PARTS)

#: Shape-channel mean (in field units, before ``shape_scale``) above which a point is inside a part
#: (f alone or g alone stays below it).
INSIDE_MEAN = 0.5
#: Ceiling of f and g (above 1 for the nose, which has A < 0); it keeps each plane's term alone below
#: the inside threshold: ceiling / 3 < INSIDE_MEAN.
FIELD_CEILING = 1.4
#: Parts whose gated colours are output features 11..31 (7 parts x 3; the beard's is the hair's).
COLOUR_FEATURE_PARTS = (HEAD, HAIR, EYES, EARS, TORSO, BACKGROUND, GLASSES)


@dataclass(frozen=True)
class DecoderDesign:
    """The constants of one teacher version's fields and decoder.

    A part's shape channel holds ``shape_scale * f`` on plane 0 and ``shape_scale * g / 2`` on planes
    1 and 2 (f, g clamped to [field_floor, FIELD_CEILING]), so its mean is ``shape_scale * m`` with
    ``m = (f + g) / 3``, and ``o = m - 1/2`` is > 0 inside. Density unit: ``softplus(density_slope o)``;
    raw density = ``density_weight`` x the sum of units + ``density_bias``. Colour gate pair of part p,
    colour k: ``softplus(3 c / colour_scale + gate_slope (o + gate_margin)) - softplus(gate_slope (o +
    gate_margin))`` with c the colour channel's mean (3 c is the colour logit), ~ ``3 c /
    colour_scale`` inside and ~ 0 outside; the RGB output weighs the pair by ``colour_scale``.
    """

    version: int
    shape_scale: float
    #: Floor of f and g. Any floor >= 0 leaves the shapes unchanged (A, B <= 2 - 2 floor is already
    #: outside once the other term is >= -1); a higher floor means a smaller channel spread, so a plane
    #: error of a given fraction of the spread moves the surface less.
    field_floor: float
    density_slope: float
    density_weight: float
    density_bias: float
    #: Colour logits enter the gates divided by ``colour_scale`` and leave them multiplied by it: a
    #: gate pair is exact while its gate term is large against its colour term, so small colour terms
    #: let moderate gate slopes gate accurately.
    colour_scale: float
    gate_slope: float
    gate_margin: float
    #: Occupancy features: sigmoid(occ_weight * density unit + occ_bias).
    occ_weight: float
    occ_bias: float
    #: Per part, the field's slope across its surface: f and g become ``c f + 3/4 (1 - c)`` (same
    #: surface, f + g = 3/2; c times the slope). Small parts (eyes, ears, glasses) have fields c
    #: times steeper than the head's, so c < 1 makes every surface about equally soft.
    surface_gain: tuple[float, ...] = (1.0,) * N_PARTS


#: The first teacher: sharp surfaces (opaque within a few millimetres), empty space at sigma ~ 1e-3;
#: gates open where o > -margin over ~2 / gate_slope (the margin keeps them open at the samples just
#: outside a surface that the marcher averages in).
V1 = DecoderDesign(
    version=1,
    shape_scale=1.0,
    field_floor=-1.0,
    density_slope=1000.0,
    density_weight=50.0,
    density_bias=-6.0,
    colour_scale=1.0,
    gate_slope=4000.0,
    gate_margin=0.005,
    occ_weight=2.0,
    occ_bias=-4.0,
)

#: The second teacher: see the module docstring; the numbers are chosen by bench/teacher_check.py.
V2 = DecoderDesign(
    version=2,
    shape_scale=50.0,
    field_floor=0.0,
    density_slope=50.0,
    density_weight=30.0,
    density_bias=-10.0,
    colour_scale=4.0,
    gate_slope=300.0,
    gate_margin=0.02,
    occ_weight=2.0,
    occ_bias=-4.0,
    # head, hair, eyes, ears, torso, background, glasses, beard: about 2 / (the part's radius across
    # its surface), relative to the head's.
    surface_gain=(1.0, 1.0, 0.15, 0.15, 0.5, 2.0, 0.1, 1.0),
)

DESIGNS: dict[int, DecoderDesign] = {1: V1, 2: V2}
#: The embedded default teacher's version.
DEFAULT_VERSION = 2


def procedural_decoder(
    version: int = DEFAULT_VERSION,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The fixed effective decoder ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` float32 of a
    teacher version.

    Hidden units: 0..7 density units ``softplus(s (mean_p - 1/2))``; unit 8 + 6p + 2k and the one after
    it are part p's gate pair for colour k; 56..63 unused (zero). Outputs: 0 raw density; 1..3 RGB
    (the sum over parts of gated logits); 4..11 (features 3..10) part occupancies; 12..32 (features
    11..31) the gated colours of :data:`COLOUR_FEATURE_PARTS`.
    """
    d = DESIGNS[version]
    k = d.shape_scale
    w0 = np.zeros((HIDDEN, N_CHANNELS))
    b0 = np.zeros(HIDDEN)
    w1 = np.zeros((N_OUT, HIDDEN))
    b1 = np.zeros(N_OUT)
    for p in range(N_PARTS):
        w0[p, p] = d.density_slope / k
        b0[p] = -d.density_slope * INSIDE_MEAN
        w1[0, p] = d.density_weight
        w1[4 + p, p] = d.occ_weight
        b1[4 + p] = d.occ_bias
        for c in range(3):
            on, off = 8 + 6 * p + 2 * c, 9 + 6 * p + 2 * c
            w0[on, N_PARTS + 3 * p + c] = 3.0 / d.colour_scale
            w0[on, p] = w0[off, p] = d.gate_slope / k
            b0[on] = b0[off] = d.gate_slope * (d.gate_margin - INSIDE_MEAN)
            w1[1 + c, on], w1[1 + c, off] = d.colour_scale, -d.colour_scale
            if p in COLOUR_FEATURE_PARTS:
                row = 12 + 3 * COLOUR_FEATURE_PARTS.index(p) + c
                w1[row, on], w1[row, off] = d.colour_scale, -d.colour_scale
    b1[0] = d.density_bias
    w0, b0, w1, b1 = (a.astype(np.float32) for a in (w0, b0, w1, b1))
    return w0, b0, w1, b1
