"""The procedural teacher's channel layout and its one hand-built decoder (see
:mod:`lp3d.teachers.procedural` for the construction): the eight parts, each with one shape and three
colour channels, and :func:`procedural_decoder`, whose density and gate units read them.
"""

from __future__ import annotations

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
