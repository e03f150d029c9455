"""One photo, ready for the encoder: detect the face, level it and crop it to the training framing."""

from __future__ import annotations

import numpy as np

from lp3d.photo.detect import detect_face
from lp3d.photo.framing import centre_crop, crop_image
from lp3d.photo.load import NoFaceError

__all__ = ["prepare_photo"]


def prepare_photo(rgb: np.ndarray, size: int, *, detect: bool, name: str) -> tuple[np.ndarray, str]:
    """(crop (size, size, 3) uint8, a one-line description) of one photo; NoFaceError without a face.

    ``detect=False`` takes the largest centred square (for photos that are already portrait crops)."""
    h, w = rgb.shape[:2]
    if not detect:
        crop = centre_crop(rgb.shape)
        return crop_image(rgb, crop, size), f"{w}x{h}, centre crop {crop.side:.0f} px (no detection)"
    found = detect_face(rgb)
    if found is None:
        raise NoFaceError(
            f"{name}: no face found; if the photo is already a centred portrait crop, pass --no-detect"
        )
    x, y, bw, bh = found.box
    eyes = f"roll {found.angle_deg:+.1f}°" if found.eyes is not None else "eyes not found, not levelled"
    more = f", {found.n_faces} face candidates (the largest clear one used)" if found.n_faces > 1 else ""
    desc = (
        f"{w}x{h}, face {bw:.0f}x{bh:.0f} at ({x:.0f}, {y:.0f}){more}, {eyes}, crop {found.crop.side:.0f} px"
    )
    return crop_image(rgb, found.crop, size), desc
