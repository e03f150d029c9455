"""The triplane: planes, decoder weights and scene bounds, as one validated value.

Layout follows EG3D (``docs/eg3d-rendering.md`` §1-§4): ``planes`` is (3, 32, H, W), each
plane a (C, H, W) image whose rows (H) are the grid_sample ``v`` coordinate and columns (W) the ``u``
coordinate. The decoder weights are EG3D's OSGDecoder weights in *effective* form (gains already
applied, see :func:`effective_decoder_weights`).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from lp3d.render.camera import validate_camera
from lp3d.render.settings import (
    DEFAULT_BOX_WARP,
    DEFAULT_RAY_END,
    DEFAULT_RAY_START,
    HIDDEN,
    N_CHANNELS,
    N_OUT,
    SceneBounds,
)

if TYPE_CHECKING:
    import lp3d_render

#: World axes (u, v) each plane samples, in EG3D's plane order: plane 0 reads (x, y), plane 1 (x, z)
#: and plane 2 (z, x). ``u`` indexes W (columns), ``v`` indexes H (rows).
#:
#: EG3D QUIRK, kept on purpose: plane 2 was meant to be YZ but EG3D's ``generate_planes`` /
#: ``project_onto_planes`` make it sample (z, x), the transpose of plane 1's (x, z). So world y is seen
#: by plane 0 alone and no plane sees the pair (y, z). Every released EG3D checkpoint (and Live 3D
#: Portrait) was trained this way (NVlabs/eg3d issue #67), so EG3D triplanes only render correctly
#: with exactly these axes.
PLANE_AXES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (2, 0))

#: For each plane, the array axis that holds world x (the plane's first coordinate indexes the last
#: axis, its second the one before): mirroring the scene in x flips exactly these axes.
PLANE_X_AXES: tuple[int, ...] = tuple(-1 if u == 0 else -2 for u, v in PLANE_AXES)


def mirror_planes(planes: Any) -> Any:
    """The triplane of the scene mirrored in x (the head's left and right swapped), for planes
    (..., 3, C, H, W) as a numpy array or torch tensor.

    Rendering the mirrored planes from the mirrored camera gives the horizontally flipped image, so a
    flipped input photo and mirrored target planes are a free training pair (the CPU recipe's
    augmentation; checked against renders in ``tests/training/test_cpu_recipe.py``)."""
    if isinstance(planes, np.ndarray):
        return np.stack([np.flip(planes[..., i, :, :, :], a) for i, a in enumerate(PLANE_X_AXES)], axis=-4)
    import torch

    return torch.stack([planes[..., i, :, :, :].flip(a) for i, a in enumerate(PLANE_X_AXES)], dim=-4)


#: Largest occupancy grid side G (the Rust bake and loader accept the same).
MAX_OCCUPANCY_RESOLUTION = 512


class TriplaneError(ValueError):
    """A ValueError about one field of a triplane; ``field`` names it (e.g. ``"planes"``, ``"w0"``)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.detail = message


_WEIGHT_SHAPES = {"w0": (HIDDEN, N_CHANNELS), "b0": (HIDDEN,), "w1": (N_OUT, HIDDEN), "b1": (N_OUT,)}


def _as_array(name: str, value: object) -> np.ndarray:
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as e:
        raise TriplaneError(name, f"cannot be converted to an array: {e}") from None


def _as_float(name: str, value: object) -> float:
    arr = _as_array(name, value)
    if arr.shape not in ((), (1,)) or arr.dtype.kind not in "fiu":
        raise TriplaneError(name, f"must be a real scalar, got dtype {arr.dtype} and shape {arr.shape}")
    return float(arr.reshape(()))


@dataclass(frozen=True, eq=False)
class TriplaneData:
    """An EG3D-format triplane, validated on construction.

    Arrays: ``planes`` (3, 32, H, W) float16 or float32 (dtype kept), ``w0`` (64, 32), ``b0`` (64,),
    ``w1`` (33, 64), ``b1`` (33,) effective decoder weights (float32 or float64 in, stored float32),
    ``camera`` optional (25,) float64 label of the input view, ``occupancy`` optional (G, G, G) float32
    grid (per cell an upper bound on the raw density, ``docs/occupancy.md``; bake it with
    ``lp3d_render.Triplane.bake_occupancy``) with ``occupancy_checksum`` optional (what it was baked
    for; checked when given), ``source`` optional short text. ``box_warp``: the
    triplane spans ``[-box_warp/2, box_warp/2]^3``; ``ray_start``/``ray_end``: the sampled depth range.
    The dataclass is frozen; arrays are not copied, so do not mutate them (call :meth:`validate` if you do).
    """

    planes: np.ndarray
    w0: np.ndarray
    b0: np.ndarray
    w1: np.ndarray
    b1: np.ndarray
    box_warp: float = DEFAULT_BOX_WARP
    ray_start: float = DEFAULT_RAY_START
    ray_end: float = DEFAULT_RAY_END
    camera: np.ndarray | None = None
    occupancy: np.ndarray | None = None
    source: str | None = field(default=None)
    #: What ``occupancy`` was baked for (:func:`occupancy_checksum`), when known: read from a file, or
    #: kept by ``dataclasses.replace``, so a grid carried over to other planes is refused.
    occupancy_checksum: int | None = None

    def __post_init__(self) -> None:
        # Normalise representations (frozen, hence object.__setattr__), then check everything.
        set_ = object.__setattr__
        set_(self, "planes", _as_array("planes", self.planes))
        for name in _WEIGHT_SHAPES:
            arr = _as_array(name, getattr(self, name))
            if arr.dtype in (np.float32, np.float64):
                arr = arr.astype(np.float32, copy=False)
            set_(self, name, arr)
        for name in ("box_warp", "ray_start", "ray_end"):
            set_(self, name, _as_float(name, getattr(self, name)))
        if self.camera is not None:
            try:
                cams, batched = validate_camera(self.camera)
            except ValueError as e:
                raise TriplaneError("camera", str(e)) from None
            if batched:
                raise TriplaneError("camera", f"must be one (25,) label, got shape {np.shape(self.camera)}")
            set_(self, "camera", cams[0])
        if self.occupancy is not None:
            occ = _as_array("occupancy", self.occupancy)
            if occ.dtype.kind == "f":
                occ = occ.astype(np.float32, copy=False)
            set_(self, "occupancy", occ)
        self.validate()

    def to_native(self) -> lp3d_render.Triplane:
        """This triplane as an ``lp3d_render.Triplane``, the GPU renderer's handle: planes (dtype
        kept), decoder, bounds and the optional camera, source and occupancy grid, so the handle
        renders and saves exactly what this value holds. A grid without ``occupancy_checksum`` is
        checked against a fresh bake (ValueError naming ``occupancy`` when it does not bound these
        planes' density). Raises ImportError without ``lp3d_render``
        (imported here: this module works without the renderer, which creates the GPU device)."""
        import lp3d_render

        return lp3d_render.Triplane(
            self.planes,
            self.w0,
            self.b0,
            self.w1,
            self.b1,
            self.box_warp,
            self.ray_start,
            self.ray_end,
            camera=self.camera,
            source=self.source,
            occupancy=self.occupancy,
            occupancy_checksum=self.occupancy_checksum,
        )

    @property
    def bounds(self) -> SceneBounds:
        """The scene bounds this triplane is rendered with (``box_warp``, ``ray_start``, ``ray_end``)."""
        return SceneBounds(self.box_warp, self.ray_start, self.ray_end)

    @property
    def plane_size(self) -> tuple[int, int]:
        """``(plane_h, plane_w)``, texels of each plane (``resolution`` is the rays per side of a render)."""
        return int(self.planes.shape[2]), int(self.planes.shape[3])

    def validate(self) -> None:
        """Raise :class:`TriplaneError` (a ValueError) naming the first bad field."""
        p = self.planes
        if p.dtype not in (np.float16, np.float32):
            raise TriplaneError(
                "planes",
                f"dtype must be float16 or float32, got {p.dtype} "
                "(cast explicitly, e.g. .astype(np.float32))",
            )
        if p.ndim != 4 or p.shape[0] != 3 or p.shape[1] != N_CHANNELS:
            raise TriplaneError("planes", f"shape must be (3, {N_CHANNELS}, H, W), got {p.shape}")
        if p.shape[2] < 2 or p.shape[3] < 2:
            raise TriplaneError("planes", f"H and W must be >= 2, got H = {p.shape[2]}, W = {p.shape[3]}")
        if not np.all(np.isfinite(p)):
            raise TriplaneError("planes", "contains NaN/Inf")
        for name, shape in _WEIGHT_SHAPES.items():
            arr = getattr(self, name)
            if arr.dtype != np.float32:
                raise TriplaneError(name, f"dtype must be float32 or float64, got {arr.dtype}")
            if arr.shape != shape:
                raise TriplaneError(name, f"shape must be {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise TriplaneError(name, "contains NaN/Inf")
        bad = self.bounds.problem()
        if bad is not None:
            raise TriplaneError(*bad)
        if self.camera is not None and (
            not isinstance(self.camera, np.ndarray)
            or self.camera.shape != (25,)
            or self.camera.dtype != np.float64
        ):
            raise TriplaneError("camera", "must be a (25,) float64 label")
        if self.occupancy is not None:
            occ = self.occupancy
            if occ.dtype != np.float32:
                raise TriplaneError(
                    "occupancy", f"dtype must be a float type (stored float32), got {occ.dtype}"
                )
            if occ.ndim != 3 or len(set(occ.shape)) != 1 or not 1 <= occ.shape[0] <= MAX_OCCUPANCY_RESOLUTION:
                raise TriplaneError(
                    "occupancy",
                    f"must be a (G, G, G) grid with 1 <= G <= {MAX_OCCUPANCY_RESOLUTION}, "
                    f"got shape {occ.shape}",
                )
            if not np.all(np.isfinite(occ)):
                raise TriplaneError("occupancy", "contains NaN/Inf")
        if self.occupancy is not None and self.occupancy_checksum is not None:
            actual = occupancy_checksum(self)
            if int(self.occupancy_checksum) != actual:
                raise TriplaneError(
                    "occupancy",
                    f"baked for other planes or another decoder (checksum {self.occupancy_checksum}, these "
                    f"give {actual}); bake it again",
                )
        if self.source is not None and not isinstance(self.source, str):
            raise TriplaneError("source", f"must be a str, got {type(self.source).__name__}")
        if self.source is not None and not _is_unicode(self.source):
            # A lone surrogate (a file name's undecodable byte, as os.fsdecode keeps it) cannot be
            # stored: the file would be one every reader refuses. lp3d.errors.safe_text makes one text.
            raise TriplaneError(
                "source", "holds a lone surrogate, not text (pass names through lp3d.errors.safe_text)"
            )


def _is_unicode(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def occupancy_checksum(tri: TriplaneData) -> int:
    """CRC-32 of the planes (as float32, (3, 32, H, W) order) and the decoder (w0, b0, w1, b1 as
    float32), all little-endian: what an occupancy grid was baked for. Stored beside the grid in the
    ``.npz`` (``occupancy_checksum``) so a grid baked for other planes is detected; the Rust
    ``Occupancy::checksum`` computes the same value."""
    crc = 0
    for arr in (tri.planes, tri.w0, tri.b0, tri.w1, tri.b1):
        crc = zlib.crc32(np.ascontiguousarray(arr, dtype="<f4").tobytes(), crc)
    return crc


def effective_decoder_weights(
    w0_stored: np.ndarray,
    b0: np.ndarray,
    w1_stored: np.ndarray,
    b1: np.ndarray,
    lr_multiplier: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """EG3D OSGDecoder stored -> effective ``w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,)``, float32.

    StyleGAN2's FullyConnectedLayer scales at run time: ``W_eff = W * (lr_multiplier / sqrt(in_features))``
    and ``b_eff = b * lr_multiplier`` (``decoder_lr_mul`` = 1 for every released config, so
    ``w0 / sqrt(32)``, ``w1 / 8``). Computed like torch's ``tensor * python_float`` on CPU (the gain
    rounded to float32, then a float32 product), so exported weights match EG3D's forward pass.
    """
    out = []
    for w, b in ((w0_stored, b0), (w1_stored, b1)):
        w = np.array(w, dtype=np.float32)
        b = np.array(b, dtype=np.float32)
        if w.ndim != 2 or b.shape != (w.shape[0],):
            raise ValueError(
                f"decoder layer shapes must be (out, in) and (out,), got {w.shape} and {b.shape}"
            )
        gain = np.float32(lr_multiplier / math.sqrt(w.shape[1]))
        out.append(w * gain)
        out.append(b if lr_multiplier == 1.0 else b * np.float32(lr_multiplier))
    w0, b0e, w1, b1e = out
    return w0, b0e, w1, b1e
