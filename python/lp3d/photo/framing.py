"""The framing the encoder was trained on: a square crop around the face, levelled by the eye line.

:func:`crop_for_face` turns a face box into a square :class:`Crop` with the framing constants below
(measured on the teacher's frontal renders); :func:`crop_image` resamples it, rotated so the eyes are
level, to the encoder's size; :func:`to_encoder_input` makes the network's input. The framing constants
live here and nowhere else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "FACE_BOX_CENTER_OFFSET_Y",
    "FACE_BOX_WIDTH_FRACTION",
    "MAX_ROLL_DEG",
    "Crop",
    "centre_crop",
    "crop_for_face",
    "crop_image",
    "to_encoder_input",
]

# --------------------------------------------------------------------------------------- framing
#: Width of OpenCV's frontal-face Haar box as a fraction of the square crop side. Measured on the
#: procedural teacher's frontal renders (EG3D's FFHQ camera: radius 2.7, focal 4.2647, looking at
#: (0, 0, 0.2)): the median over 17 identities is 0.48 (range 0.40-0.68, the box size is noisy).
FACE_BOX_WIDTH_FRACTION = 0.48
#: Vertical position of the face box centre relative to the crop centre, as a fraction of the crop
#: side; negative is above the centre (the camera looks slightly below the face centre). Same
#: measurement: median -0.045 (range -0.066 to -0.016). Horizontally the face box is centred.
FACE_BOX_CENTER_OFFSET_Y = -0.045
#: Eye-line angles beyond this are treated as a failed eye detection (no rotation).
MAX_ROLL_DEG = 30.0


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


def crop_for_face(box: tuple[float, float, float, float], angle_deg: float = 0.0) -> Crop:
    """The training framing around a face box ``(x, y, w, h)``: side ``w / FACE_BOX_WIDTH_FRACTION``,
    the box centre at ``FACE_BOX_CENTER_OFFSET_Y * side`` from the crop centre along the levelled
    vertical."""
    x, y, w, h = box
    side = w / FACE_BOX_WIDTH_FRACTION
    fx, fy = x + (w - 1) / 2.0, y + (h - 1) / 2.0
    # Crop centre = face centre - R(angle) @ (0, offset * side): the offset is vertical in the level frame.
    a = math.radians(angle_deg)
    d = FACE_BOX_CENTER_OFFSET_Y * side
    return Crop(cx=fx + math.sin(a) * d, cy=fy - math.cos(a) * d, side=side, angle_deg=angle_deg)


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
