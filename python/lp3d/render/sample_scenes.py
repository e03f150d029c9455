"""Hand-built triplanes with known geometry, for docs, demos and tests.

Because of EG3D's plane quirk (``lp3d.render.triplane.PLANE_AXES``) a channel's value at a point is
``(P0(x, y) + P1(x, z) + P2(z, x)) / 3``. A sphere ``|q|^2 < r^2`` has no y·z term, so it fits one
channel exactly. Beyond the box some planes read zero (only P0 beyond it in z, only P1 and P2 beyond
it in y, none beyond it in x), so each plane's term alone must stay below the inside threshold.
Otherwise the sphere would reappear as a floater outside the box.
"""

from __future__ import annotations

import numpy as np

from lp3d.render.triplane import TriplaneData

#: Inside threshold on channel 0 and the per-plane constants that keep single planes below it.
_TAU, _A, _B = 0.5, 1.2, 0.6


def _grid(size: int) -> np.ndarray:
    """Texel-centre coordinates in [-1, 1] (grid_sample, align_corners=False)."""
    return (2.0 * np.arange(size) + 1.0) / size - 1.0


def coloured_sphere(size: int = 128, radius: float = 0.3, box_warp: float = 1.0) -> TriplaneData:
    """A solid sphere of world ``radius`` at the origin, with a coloured checker/stripe pattern.

    Channel 0 is the sphere's signed occupancy (> ``_TAU`` inside). Channels 1-3 are colour logits:
    a checker on (x, y), stripes on (x, z) and a shading gradient. The decoder is hand-built:
    hidden unit 0 turns channel 0 into a sharp occupancy, units 1-3 pass the colours through
    softplus in its linear range, and the other units and channels carry smooth copies as extra
    features.
    """
    rq = 2.0 * radius / box_warp  # radius in normalised plane coordinates
    k = (_A + 2 * _B - 3 * _TAU) / rq**2
    c = _grid(size)
    u, v = np.meshgrid(c, c, indexing="xy")  # u: columns (first plane axis), v: rows (second axis)
    planes = np.zeros((3, 32, size, size), np.float64)
    # Plane 0 samples (x, y); plane 1 (x, z); plane 2 (z, x). See lp3d.render.triplane.PLANE_AXES.
    planes[0, 0] = _A - k * (u**2 + v**2)
    planes[1, 0] = _B - k * v**2 / 2  # z is plane 1's v ...
    planes[2, 0] = _B - k * u**2 / 2  # ... and plane 2's u
    checker = np.sign(np.sin(4.5 * np.pi * u) * np.sin(4.5 * np.pi * v))
    planes[0, 1] = 3.0 * checker  # red: checker seen from the front
    planes[1, 2] = 1.5 * np.sin(6.0 * np.pi * v)  # green: stripes along z
    planes[2, 2] = 1.5 * np.sin(6.0 * np.pi * u)
    planes[0, 3] = 3.0 * (0.8 * v - 0.3)  # blue: a vertical gradient (top of the image is -y)
    for ch in range(4, 32):  # extra feature channels: smooth mixtures of the above
        planes[:, ch] = 0.5 * planes[:, (ch % 3) + 1] + 0.1 * planes[:, 0]

    w0 = np.zeros((64, 32), np.float32)
    b0 = np.zeros(64, np.float32)
    w1 = np.zeros((33, 64), np.float32)
    b1 = np.zeros(33, np.float32)
    sharp = 400.0
    w0[0, 0], b0[0] = sharp, -sharp * _TAU  # occupancy unit
    w1[0, 0], b1[0] = 3.0, -6.0  # raw density: ~30 inside, -6 outside (softplus(-7) ~ 1e-3)
    for j in range(1, 33):  # colour/feature units in softplus's linear range: h ~ f + 4
        w0[j, (j - 1) % 32], b0[j] = 1.0, 4.0
        w1[j, j], b1[j] = 1.5, -6.0
    return TriplaneData(
        planes=planes.astype(np.float32),
        w0=w0,
        b0=b0,
        w1=w1,
        b1=b1,
        box_warp=box_warp,
        source=f"lp3d.render.sample_scenes.coloured_sphere(size={size}, radius={radius})",
    )
