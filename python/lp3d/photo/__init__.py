"""Photos in: safe image loading, face detection, levelling and the crop the encoder was trained on.

The encoder only works on images framed like its training data (the teacher's frontal renders), so a
photo is read, detected, levelled and cropped to that framing before encoding:

1. :mod:`~lp3d.photo.load`: :func:`load_image` reads any Pillow format safely, with notes;
2. :mod:`~lp3d.photo.detect`: :func:`detect_face` finds the largest face and its eye line;
3. :mod:`~lp3d.photo.framing`: :func:`crop_for_face` and :func:`crop_image` make the training framing;
4. :mod:`~lp3d.photo.prepare`: :func:`prepare_photo` does 2-3 for one photo, with a description;
5. :mod:`~lp3d.photo.video`: :func:`read_video` reads a video's frames (bundled ffmpeg) and
   :func:`smooth_crops` steadies the per-frame crops.

May import: :mod:`lp3d.errors` only (OpenCV, Pillow and imageio-ffmpeg lazily). The names below are
re-exported so ``from lp3d.photo import load_image`` works.
"""

from lp3d.photo.detect import DETECT_MAX_SIDE, FaceDetection, detect_face
from lp3d.photo.framing import (
    FACE_BOX_CENTER_OFFSET_Y,
    FACE_BOX_WIDTH_FRACTION,
    MAX_ROLL_DEG,
    Crop,
    centre_crop,
    crop_for_face,
    crop_image,
    to_encoder_input,
)
from lp3d.photo.load import (
    IMAGE_SUFFIXES,
    MAX_PIXELS,
    MAX_SIDE,
    MIN_SIDE,
    PHOTO_SUFFIXES,
    NoFaceError,
    PhotoError,
    load_image,
)
from lp3d.photo.prepare import prepare_photo

__all__ = [
    "DETECT_MAX_SIDE",
    "FACE_BOX_CENTER_OFFSET_Y",
    "FACE_BOX_WIDTH_FRACTION",
    "IMAGE_SUFFIXES",
    "MAX_PIXELS",
    "MAX_ROLL_DEG",
    "MAX_SIDE",
    "MIN_SIDE",
    "PHOTO_SUFFIXES",
    "Crop",
    "FaceDetection",
    "NoFaceError",
    "PhotoError",
    "centre_crop",
    "crop_for_face",
    "crop_image",
    "detect_face",
    "load_image",
    "prepare_photo",
    "to_encoder_input",
]
