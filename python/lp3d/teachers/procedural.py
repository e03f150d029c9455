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
``softplus(c + beta (o + m)) - softplus(beta (o + m))`` equal to the (scaled) logit ``c`` inside the part
(``o`` = shape mean - 1/2 > -m) and to 0 elsewhere: 8 + 8 x 3 x 2 = 56 of the 64 hidden units.
Output features 3..31 are the part occupancies and per-part colours, so they carry meaning too.

Two versions share this construction (:class:`~lp3d.teachers.procedural_decoder.DecoderDesign`):

* **v2, the default**, is built to be a fair stand-in for EG3D: sharpness lives in the
  planes (shape channels scaled by 50, each part's field slope evened out by its surface gain), the
  decoder's weights stay below 10 in the first layer, and surfaces gather their opacity over about 5 cm,
  so they are soft on the 48 + 48 sampler's scale (2.2 cm between coarse samples) and a plane error
  moves a surface a little instead of flipping a part. Glasses are thicker and hair and beard edges
  softer than in v1, for the same reason. ``bench/teacher_check.py`` measures both.
* **v1** keeps the first teacher bit for bit: the shipped ``small`` model was distilled from it.

The code: :mod:`~lp3d.teachers.procedural_decoder` (channel layout, decoder),
:mod:`~lp3d.teachers.procedural_identity` (:class:`HeadParams` from a seed),
:mod:`~lp3d.teachers.procedural_fields` and :mod:`~lp3d.teachers.procedural_builder` (the parts' fields);
this module holds :class:`ProceduralTeacher` and re-exports the public names.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lp3d.render.settings import (
    DEFAULT_BOX_WARP,
    DEFAULT_RAY_END,
    DEFAULT_RAY_START,
    N_CHANNELS,
)
from lp3d.render.triplane import TriplaneData
from lp3d.teachers.procedural_builder import HeadBuilder
from lp3d.teachers.procedural_decoder import (
    BACKGROUND,
    BEARD,
    DEFAULT_VERSION,
    DESIGNS,
    EARS,
    EYES,
    FIELD_CEILING,
    GLASSES,
    HAIR,
    HEAD,
    N_PARTS,
    PARTS,
    TORSO,
    procedural_decoder,
)
from lp3d.teachers.procedural_fields import Textures
from lp3d.teachers.procedural_identity import HAIRSTYLES, PATTERNS, Hairstyle, HeadParams, Pattern

#: Plane resolution of the emitted triplanes (EG3D FFHQ: 256).
RESOLUTION = 256
#: The teacher versions (:mod:`lp3d.teachers.procedural_decoder`): 2 is the default; 1 is kept because
#: the shipped ``small`` model was distilled from it and its evaluation is reproduced against it.
TEACHER_VERSIONS = tuple(sorted(DESIGNS))

__all__ = [
    "BACKGROUND",
    "BEARD",
    "EARS",
    "EYES",
    "GLASSES",
    "HAIR",
    "HAIRSTYLES",
    "HEAD",
    "N_PARTS",
    "PARTS",
    "PATTERNS",
    "RESOLUTION",
    "TEACHER_VERSIONS",
    "TORSO",
    "Hairstyle",
    "HeadParams",
    "Pattern",
    "ProceduralTeacher",
    "procedural_decoder",
]


def _field(a: np.ndarray | float, gain: float, lo: float, hi: float) -> np.ndarray:
    """A plane's shape field from the part's quadric-like ``a`` (A or B): ``1 - a/2`` through the
    surface gain (``gain (1 - a/2) + 3/4 (1 - gain)``: the same surface f + g = 3/2, ``gain`` times
    the slope), clamped to [lo, hi], float32. The gain acts before the clamp, so far from the part
    the field still reaches the floor."""
    a = np.asarray(a, dtype=np.float32)
    f = 1.0 - 0.5 * a if gain == 1.0 else gain * (1.0 - 0.5 * a) + 0.75 * (1.0 - gain)
    return np.clip(f, lo, hi, dtype=np.float32)


# ---------------------------------------------------------------------------------------- teacher
class ProceduralTeacher:
    """Stylised heads as EG3D triplanes, built in closed form: the embedded default teacher.

    ``sample(seed)`` draws :class:`HeadParams` from the seed and builds the triplane with :meth:`build`
    (quick enough to draw identities during training). Coordinate grids, textures and the decoder are
    made once per teacher.
    """

    def __init__(self, resolution: int = RESOLUTION, *, version: int = DEFAULT_VERSION) -> None:
        if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 16:
            raise ValueError(f"resolution must be an int >= 16, got {resolution!r}")
        if type(version) is not int or version not in DESIGNS:
            raise ValueError(f"version must be one of {list(DESIGNS)}, got {version!r}")
        self.resolution = resolution
        self.version = version
        self._design = DESIGNS[version]
        self.box_warp = DEFAULT_BOX_WARP
        # Texel centres in world units (grid_sample with align_corners=False).
        c = ((2.0 * np.arange(resolution) + 1.0) / resolution - 1.0) * (self.box_warp / 2.0)
        self._coords = c.astype(np.float32)
        self._textures = Textures(self._coords)
        self._decoder = procedural_decoder(version)

    def decoder(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The fixed decoder shared by every identity (copies): w0 (64, 32), b0 (64,), w1 (33, 64),
        b1 (33,)."""
        w0, b0, w1, b1 = (a.copy() for a in self._decoder)
        return w0, b0, w1, b1

    def sample(self, seed: int) -> TriplaneData:
        """Triplane (3, 32, R, R) float32 of identity ``seed``; ``source`` is ``"procedural seed N"``."""
        return self.build(HeadParams.sample(seed), source=self.source(seed))

    def source(self, seed: int) -> str:
        """The ``source`` text of identity ``seed``: ``"procedural seed N"`` (v1: ``"procedural v1 seed
        N"``)."""
        version = "" if self.version == DEFAULT_VERSION else f" v{self.version}"
        return f"procedural{version} seed {int(seed)}"

    def sample_batch(self, seeds: Sequence[int]) -> list[TriplaneData]:
        """``[sample(s) for s in seeds]``."""
        return [self.sample(s) for s in seeds]

    def build(self, params: HeadParams, *, source: str | None = None) -> TriplaneData:
        """The triplane of an explicit identity."""
        parts = HeadBuilder(params, self._coords, self._textures, version=self.version).parts()
        R = self.resolution
        d = self._design
        lo, hi, k = d.field_floor, FIELD_CEILING, d.shape_scale
        planes = np.empty((3, N_CHANNELS, R, R), dtype=np.float32)
        for p, part in enumerate(parts):
            # f = 1 - A/2 and g = 1 - B/2 (each through the part's surface gain, then clamped), scaled
            # by k: the shape channel's mean is k (f + g) / 3 (planes 1 and 2 hold k g/2 each), and the
            # colour logit 3 * mean is fc + gc.
            c = d.surface_gain[p]
            colours = slice(N_PARTS + 3 * p, N_PARTS + 3 * p + 3)
            f, fc = planes[0, p], planes[0, colours]
            if part.window is None:
                f[...] = _field(part.A, c, lo, hi)
                fc[...] = part.fc
            else:
                rows, cols = part.window
                f[...] = lo
                f[rows, cols] = _field(part.A, c, lo, hi)
                fc[...] = 0.0
                fc[:, rows, cols] = part.fc
            f *= k
            # Plane 2 samples (z, x): it gets the transposes. Fields that vary along one axis only are
            # stored as (R, 1) or (1, R), so most transposes are cheap broadcasts.
            g = (0.5 * _field(part.B, c, lo, hi)) * np.float32(k)
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
