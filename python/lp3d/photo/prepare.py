"""One photo, ready for the encoder: find the face and its landmarks, put it in the training framing.

:func:`detect_face` finds the largest face (:mod:`lp3d.photo.faces`) and aligns it
(:mod:`lp3d.photo.alignment`): the crop that frames it as the encoder's training renders and the
camera it was seen from. :func:`prepare_photo` does that for one photo and says what it found, or
refuses a photo the encoder cannot lift (no face, a face too small, a face turned too far) in one line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lp3d.photo.alignment import MAX_YAW_DEG, FaceAlignment, align_face
from lp3d.photo.faces import MIN_FACE_PX, Face, find_faces
from lp3d.photo.framing import Crop, centre_crop, crop_image
from lp3d.photo.load import NoFaceError, PhotoError

__all__ = ["FaceDetection", "PreparedPhoto", "detect_face", "prepare_photo"]

#: Yaw (degrees) beyond which a face is refused: the search's edge, past the training views' ±49°.
REFUSED_YAW_DEG = MAX_YAW_DEG - 1.0


@dataclass(frozen=True)
class FaceDetection:
    """The face lifted from a photo (the largest found), how many faces were found, and its alignment
    (camera and training-framed crop)."""

    face: Face
    n_faces: int
    alignment: FaceAlignment

    @property
    def crop(self) -> Crop:
        return self.alignment.crop


@dataclass(frozen=True)
class PreparedPhoto:
    """A photo ready for the encoder: the ``image`` (size, size, 3) uint8 in the training framing, a
    one-line ``description`` and, unless detection was skipped, the face's ``detection`` (its camera
    is the one the refinement starts from)."""

    image: np.ndarray
    description: str
    detection: FaceDetection | None

    @property
    def pose(self) -> tuple[float, float] | None:
        """``(yaw, pitch)`` in degrees of the photo's look-at camera, or None without detection."""
        if self.detection is None:
            return None
        a = self.detection.alignment
        return (a.yaw_deg, a.pitch_deg)


def detect_face(rgb: np.ndarray) -> FaceDetection | None:
    """The largest face in ``rgb`` (H, W, 3) uint8, aligned; None when there is none."""
    faces = find_faces(rgb)
    if not faces:
        return None
    return FaceDetection(face=faces[0], n_faces=len(faces), alignment=align_face(faces[0].landmarks))


def prepare_photo(rgb: np.ndarray, size: int, *, detect: bool, name: str) -> PreparedPhoto:
    """One photo in the training framing at ``size``²; NoFaceError without a usable face.

    ``detect=False`` takes the largest centred square (for photos that are already portrait crops)."""
    h, w = rgb.shape[:2]
    if not detect:
        crop = centre_crop(rgb.shape)
        desc = f"{w}x{h}, centre crop {crop.side:.0f} px (no detection)"
        return PreparedPhoto(crop_image(rgb, crop, size), desc, None)
    found = detect_face(rgb)
    if found is None:
        raise NoFaceError(
            f"{name}: no face found (a frontal or turned face is needed; profiles are not found); if the "
            "photo is already a centred portrait crop, pass --no-detect"
        )
    span = found.face.eye_span_px
    if span < MIN_FACE_PX:
        raise NoFaceError(
            f"{name}: the face is too small ({span:.0f} px between the outer eye corners, at least "
            f"{MIN_FACE_PX:.0f} needed); use a larger photo of it"
        )
    a = found.alignment
    if abs(a.yaw_deg) >= REFUSED_YAW_DEG:
        raise PhotoError(
            f"{name}: the face is turned too far (yaw beyond ±{REFUSED_YAW_DEG:.0f}°); the encoder "
            "lifts faces seen from the front or the side up to about ±50°"
        )
    x, y, bw, bh = found.face.box
    more = f", {found.n_faces} faces (the largest used)" if found.n_faces > 1 else ""
    desc = (
        f"{w}x{h}, face {bw:.0f}x{bh:.0f} at ({x:.0f}, {y:.0f}){more}, yaw {a.yaw_deg:+.0f}° pitch "
        f"{a.pitch_deg:+.0f}° roll {a.roll_deg:+.0f}°, crop {a.crop.side:.0f} px"
    )
    return PreparedPhoto(crop_image(rgb, a.crop, size), desc, found)
