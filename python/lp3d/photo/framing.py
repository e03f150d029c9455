"""A square, levelled region of a photo (:class:`Crop`), resampled to the encoder's size.

:mod:`lp3d.photo.alignment` decides where the crop lies (from the face's landmarks);
:func:`crop_image` resamples it, rotated so the face is upright; :func:`to_encoder_input` makes the
network's input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "Crop",
    "centre_crop",
    "crop_image",
    "to_encoder_input",
]


@dataclass(frozen=True)
class Crop:
    """A square region of a source image: centre ``(cx, cy)`` and ``side`` in source pixels, rotated by
    ``angle_deg`` (the eye-line angle in image coordinates, y down; positive when the right-hand eye is
    lower). :func:`crop_image` levels it, so content rotated by ``angle_deg`` comes out upright."""

    cx: float
    cy: float
    side: float
    angle_deg: float = 0.0

    def matrix(self, size: int) -> np.ndarray:
        """The (2, 3) affine map from source pixels to ``size``² crop pixels (OpenCV's convention)."""
        s = size / self.side
        a = math.radians(-self.angle_deg)  # undo the tilt: R(-angle)
        c, si = math.cos(a), math.sin(a)
        lin = s * np.array([[c, -si], [si, c]])
        # OpenCV pixel centres are at integer coordinates: the crop centre maps to (size - 1) / 2.
        t = np.array([(size - 1) / 2.0, (size - 1) / 2.0]) - lin @ np.array([self.cx, self.cy])
        return np.concatenate([lin, t[:, None]], axis=1)


def centre_crop(shape: tuple[int, ...]) -> Crop:
    """The largest centred square of an image of ``shape`` (H, W, ...) (used with ``--no-detect``)."""
    h, w = int(shape[0]), int(shape[1])
    return Crop(cx=(w - 1) / 2.0, cy=(h - 1) / 2.0, side=float(min(h, w)))


def crop_image(rgb: np.ndarray, crop: Crop, size: int) -> np.ndarray:
    """Resample ``crop`` of ``rgb`` (H, W, 3) uint8 to (size, size, 3) uint8, levelled.

    Area-averages first when the crop shrinks the image more than 2x (bilinear alone would alias);
    areas outside the image are filled by reflection (as FFHQ-style alignment pads).
    """
    import cv2

    src = rgb
    c = crop
    shrink = size / c.side
    if shrink < 0.5:
        # Pre-shrink the whole image so the warp itself downsamples at most 2x.
        r = 2.0 * shrink
        h, w = rgb.shape[:2]
        nw, nh = max(1, round(w * r)), max(1, round(h * r))
        src = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
        rx, ry = nw / w, nh / h
        # INTER_AREA maps pixel centres as (p + 0.5) * r - 0.5.
        c = replace(c, cx=(c.cx + 0.5) * rx - 0.5, cy=(c.cy + 0.5) * ry - 0.5, side=c.side * (rx + ry) / 2.0)
    out = cv2.warpAffine(
        src, c.matrix(size), (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101
    )
    return np.ascontiguousarray(out)


def to_encoder_input(crops: np.ndarray) -> np.ndarray:
    """(B, S, S, 3) uint8 crops -> (B, 3, S, S) float32 in [-1, 1] (EG3D's image range)."""
    x = np.asarray(crops, dtype=np.float32) / 127.5 - 1.0
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))
