"""Finding the face: the largest frontal face (OpenCV's bundled Haar cascades) and its eye line.

:func:`detect_face` runs on a grey copy downscaled to at most :data:`DETECT_MAX_SIDE`, then looks for
the two eyes inside the face box to level the crop (:mod:`lp3d.photo.framing`).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from lp3d.photo.framing import MAX_ROLL_DEG, Crop, crop_for_face
from lp3d.photo.load import PhotoError

__all__ = ["DETECT_MAX_SIDE", "FaceDetection", "detect_face"]

#: Detection runs on a copy whose longer side is at most this (Haar cascades need no more, and
#: a 100 MP photo would take minutes at full size).
DETECT_MAX_SIDE = 1024


@dataclass(frozen=True)
class FaceDetection:
    """A detected face: its Haar box ``(x, y, w, h)`` in source pixels, the eye centres if both were
    found, the number of faces seen and the crop made from it (:func:`crop_for_face`)."""

    box: tuple[float, float, float, float]
    eyes: tuple[tuple[float, float], tuple[float, float]] | None
    n_faces: int
    crop: Crop

    @property
    def angle_deg(self) -> float:
        return self.crop.angle_deg


_CASCADES: dict[str, object] = {}
_MAX_SLOPE = math.tan(math.radians(MAX_ROLL_DEG))


def _cascade(name: str) -> object:
    """A cached OpenCV Haar cascade from the files bundled with opencv-python."""
    if name not in _CASCADES:
        try:
            import cv2
        except ImportError as e:  # pragma: no cover - a packaging problem, reported clearly
            raise PhotoError(
                f"face detection needs OpenCV (pip install 'opencv-python-headless<5'): {e}"
            ) from None
        if not hasattr(cv2, "CascadeClassifier"):
            raise PhotoError(
                f"this OpenCV ({cv2.__version__}) has no Haar cascades (removed in OpenCV 5); "
                "install 'opencv-python-headless<5' or pass --no-detect"
            )
        path = os.path.join(cv2.data.haarcascades, name)
        clf = cv2.CascadeClassifier(path)
        if clf.empty():
            raise PhotoError(f"cannot load OpenCV's Haar cascade {path}")
        _CASCADES[name] = clf
    return _CASCADES[name]


def _eye_pair(eyes: np.ndarray, face_w: float) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The most plausible (left-in-image, right-in-image) eye pair of candidate boxes, in face-box
    coordinates, or None: one eye each side of the box centre, 0.2-0.7 face widths apart, and the
    line through them within MAX_ROLL_DEG of level."""
    centres = [(x + w / 2.0, y + h / 2.0, w * h) for x, y, w, h in np.asarray(eyes).reshape(-1, 4)]
    best: tuple[float, tuple[tuple[float, float], tuple[float, float]]] | None = None
    for lx, ly, la in centres:
        for rx, ry, ra in centres:
            dx, dy = rx - lx, ry - ly
            if not (
                lx < face_w / 2 < rx and 0.2 * face_w <= dx <= 0.7 * face_w and abs(dy) <= _MAX_SLOPE * dx
            ):
                continue
            score = la + ra  # larger boxes are the more confident detections
            if best is None or score > best[0]:
                best = (score, ((lx, ly), (rx, ry)))
    return None if best is None else best[1]


def detect_face(rgb: np.ndarray) -> FaceDetection | None:
    """The largest frontal face in ``rgb`` (H, W, 3) uint8 with its levelled training-framing crop.

    Detection runs on a grey copy downscaled to :data:`DETECT_MAX_SIDE`; eyes are searched in the
    upper 60 % of the face box to level the eye line (no rotation when no plausible pair is found).
    Returns None when there is no face.
    """
    import cv2

    face_clf = _cascade("haarcascade_frontalface_default.xml")
    eye_clf = _cascade("haarcascade_eye.xml")
    h, w = rgb.shape[:2]
    scale = min(1.0, DETECT_MAX_SIDE / max(h, w))
    small = (
        rgb
        if scale == 1.0
        else cv2.resize(rgb, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    )
    grey = cv2.equalizeHist(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY))
    min_face = max(24, min(grey.shape) // 20)  # faces down to 5 % of the shorter side
    faces, hits = face_clf.detectMultiScale2(  # type: ignore[attr-defined]
        grey, scaleFactor=1.1, minNeighbors=5, minSize=(min_face, min_face)
    )
    if len(faces) == 0:
        return None
    # The largest of the confident faces: a false positive (clothing, background) is often large but
    # gathers few overlapping detections ("neighbours") compared with a real face.
    hits = np.asarray(hits).reshape(-1)
    confident = [f for f, n in zip(faces, hits, strict=True) if n >= 0.5 * hits.max()]
    x, y, fw, fh = (int(v) for v in max(confident, key=lambda f: int(f[2]) * int(f[3])))
    roi = grey[y : y + int(0.6 * fh), x : x + fw]
    eye_min, eye_max = max(6, fw // 10), max(8, fw // 3)
    eyes = eye_clf.detectMultiScale(
        roi, scaleFactor=1.05, minNeighbors=3, minSize=(eye_min, eye_min), maxSize=(eye_max, eye_max)
    )  # type: ignore[attr-defined]
    pair = _eye_pair(eyes, fw) if len(eyes) >= 2 else None
    angle = 0.0
    eyes_src = None
    if pair is not None:
        (lx, ly), (rx, ry) = pair
        a = math.degrees(math.atan2(ry - ly, rx - lx))
        if abs(a) <= MAX_ROLL_DEG:
            angle = a
            eyes_src = ((x + lx) / scale, (y + ly) / scale), ((x + rx) / scale, (y + ry) / scale)
    box = (x / scale, y / scale, fw / scale, fh / scale)
    return FaceDetection(box=box, eyes=eyes_src, n_faces=len(faces), crop=crop_for_face(box, angle))
