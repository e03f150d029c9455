"""Finding faces offline: dlib's HOG face detector and its five-point landmark model.

The models are the CC0 files of the ``face_recognition_models`` package (installed with lp3d), read
from disk; nothing is downloaded. dlib itself comes from the ``dlib-bin`` wheels. The 68-point model in
the same package was trained on data that forbids commercial use, so lp3d never loads it.

:func:`find_faces` returns every face with its five landmarks (:data:`LANDMARK_NAMES`), largest first;
:func:`face_descriptor` gives dlib's 128-number identity descriptor of a face (for measuring whether a
lifted head is still its person, :mod:`lp3d.evaluation.photos`).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.photo.load import PhotoError

__all__ = [
    "DETECT_MAX_SIDE",
    "LANDMARK_NAMES",
    "MIN_FACE_PX",
    "Face",
    "face_descriptor",
    "face_model_path",
    "find_faces",
]

#: Detection runs on a copy whose longer side is at most this (a 100 MP photo would take minutes at
#: full size); landmarks are then placed on the full-resolution image.
DETECT_MAX_SIDE = 1024
#: The HOG detector's smallest face is about 80 px; images whose shorter side is below this are
#: upsampled twice before detection so that faces down to ~40 px are found.
UPSAMPLE_BELOW = 400
#: Faces narrower than this (eye corner to eye corner, in source pixels, ~ a third of the face width)
#: hold too little for a 512² crop and are refused (PhotoError) rather than lifted from a blur.
MIN_FACE_PX = 16.0

#: dlib's five-point landmarks, in its order. "Left"/"right" are as the image shows them (the
#: person's right eye is on the image's left). The nose point is the base of the nose, under its tip.
LANDMARK_NAMES = (
    "right_eye_outer",
    "right_eye_inner",
    "left_eye_outer",
    "left_eye_inner",
    "nose_base",
)

#: File of each model lp3d uses, inside ``face_recognition_models/models``.
MODEL_FILES = {
    "landmarks": "shape_predictor_5_face_landmarks.dat",
    "descriptor": "dlib_face_recognition_resnet_model_v1.dat",
}


@dataclass(frozen=True)
class Face:
    """One detected face: its detector ``box`` ``(x, y, w, h)`` and ``landmarks`` (5, 2) float64, both
    in source pixels (x right, y down; pixel centres at integers), and the detector's ``score``."""

    box: tuple[float, float, float, float]
    landmarks: np.ndarray
    score: float

    @property
    def eye_span_px(self) -> float:
        """Distance between the two outer eye corners, in source pixels (the face's scale)."""
        return float(np.linalg.norm(self.landmarks[0] - self.landmarks[2]))


def face_model_path(kind: str) -> Path:
    """The model file of ``kind`` (``"landmarks"`` or ``"descriptor"``) from the installed
    ``face_recognition_models`` package, found without importing it (its ``__init__`` needs
    setuptools' ``pkg_resources``). PhotoError with the fix when the package or file is missing."""
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise PhotoError(
            "face detection needs dlib's models: pip install face_recognition_models dlib-bin "
            "(or pass --no-detect for a photo that is already a centred portrait crop)"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "models" / MODEL_FILES[kind]
    if not path.is_file():
        raise PhotoError(f"dlib's {kind} model is missing: {path}; reinstall face_recognition_models")
    return path


_MODELS: dict[str, Any] = {}


def _dlib() -> Any:
    try:
        import dlib
    except ImportError as e:
        raise PhotoError(
            f"face detection needs dlib: pip install dlib-bin ({e}); or pass --no-detect for a photo "
            "that is already a centred portrait crop"
        ) from None
    return dlib


def _model(kind: str) -> Any:
    """A cached dlib model: ``"detector"`` (HOG, built into dlib), ``"landmarks"`` or ``"descriptor"``."""
    if kind not in _MODELS:
        dlib = _dlib()
        if kind == "detector":
            _MODELS[kind] = dlib.get_frontal_face_detector()
        else:
            path = face_model_path(kind)
            try:
                load = dlib.shape_predictor if kind == "landmarks" else dlib.face_recognition_model_v1
                _MODELS[kind] = load(str(path))
            except RuntimeError as e:
                raise PhotoError(f"cannot load dlib's {kind} model {path}: {e}") from None
    return _MODELS[kind]


def _landmarks(rgb: np.ndarray, box: tuple[float, float, float, float]) -> Any:
    """dlib's full_object_detection of the five landmarks in ``box`` of ``rgb``."""
    dlib = _dlib()
    x, y, w, h = box
    rect = dlib.rectangle(round(x), round(y), round(x + w - 1), round(y + h - 1))
    return _model("landmarks")(rgb, rect)


def find_faces(rgb: np.ndarray) -> list[Face]:
    """Every face in ``rgb`` (H, W, 3) uint8 with its five landmarks, the largest first.

    The HOG detector runs on a copy downscaled to :data:`DETECT_MAX_SIDE` (upsampled when small, so
    faces down to about 40 px are found); landmarks are placed on the full-resolution image. Frontal
    and turned faces up to about 45-50° of yaw are found; profiles are not."""
    import cv2

    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w = img.shape[:2]
    scale = min(1.0, DETECT_MAX_SIDE / max(h, w))
    small = (
        img
        if scale == 1.0
        else cv2.resize(img, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    )
    upsample = 1 if min(small.shape[:2]) < UPSAMPLE_BELOW else 0
    rects, scores, _ = _model("detector").run(small, upsample, 0.0)
    faces = []
    for r, s in zip(rects, scores, strict=True):
        box = (r.left() / scale, r.top() / scale, r.width() / scale, r.height() / scale)
        shape = _landmarks(img, box)
        pts = np.array([[p.x, p.y] for p in shape.parts()], np.float64)
        faces.append(Face(box=box, landmarks=pts, score=float(s)))
    faces.sort(key=lambda f: -f.box[2] * f.box[3])
    return faces


def face_descriptor(rgb: np.ndarray, face: Face) -> np.ndarray:
    """dlib's identity descriptor (128,) float64 of ``face`` in ``rgb`` (H, W, 3) uint8: two photos of
    one person lie about 0.35-0.45 apart (Euclidean), different people beyond dlib's 0.6 threshold."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    shape = _landmarks(img, face.box)
    return np.asarray(_model("descriptor").compute_face_descriptor(img, shape), np.float64)
