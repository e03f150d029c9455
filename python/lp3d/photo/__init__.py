"""Photos in: safe image loading, faces and their landmarks, the camera and the crop the encoder
was trained on.

The encoder only works on images framed like its training data (the teacher's renders by EG3D's FFHQ
look-at camera), so a photo is read, its face found and put in that framing before encoding:

1. :mod:`~lp3d.photo.load`: :func:`load_image` reads any Pillow format safely, with notes;
2. :mod:`~lp3d.photo.faces`: :func:`find_faces` finds faces and their five landmarks (dlib, offline);
3. :mod:`~lp3d.photo.alignment`: :func:`align_face` finds the face's camera (yaw, pitch) and the crop
   that frames it as in training;
4. :mod:`~lp3d.photo.framing`: :class:`Crop`, :func:`crop_image` resamples it, levelled;
5. :mod:`~lp3d.photo.prepare`: :func:`prepare_photo` does 2-4 for one photo, with a description;
6. :mod:`~lp3d.photo.video`: :func:`read_video` reads a video's frames (bundled ffmpeg) and
   :func:`smooth_crops` steadies the per-frame crops.

May import: :mod:`lp3d.errors` and :mod:`lp3d.render` (the camera convention); dlib, OpenCV, Pillow
and imageio-ffmpeg lazily. The names below are re-exported so ``from lp3d.photo import load_image``
works.
"""

from lp3d.photo.alignment import FACE_TEMPLATE, FaceAlignment, align_face
from lp3d.photo.faces import DETECT_MAX_SIDE, LANDMARK_NAMES, Face, face_descriptor, find_faces
from lp3d.photo.framing import Crop, centre_crop, crop_image, to_encoder_input
from lp3d.photo.load import (
    MAX_PIXELS,
    MAX_SIDE,
    MIN_SIDE,
    PHOTO_SUFFIXES,
    NoFaceError,
    PhotoError,
    decode_image,
    load_image,
)
from lp3d.photo.prepare import FaceDetection, PreparedPhoto, detect_face, prepare_photo

__all__ = [
    "DETECT_MAX_SIDE",
    "FACE_TEMPLATE",
    "LANDMARK_NAMES",
    "MAX_PIXELS",
    "MAX_SIDE",
    "MIN_SIDE",
    "PHOTO_SUFFIXES",
    "Crop",
    "Face",
    "FaceAlignment",
    "FaceDetection",
    "NoFaceError",
    "PhotoError",
    "PreparedPhoto",
    "align_face",
    "centre_crop",
    "crop_image",
    "decode_image",
    "detect_face",
    "face_descriptor",
    "find_faces",
    "load_image",
    "prepare_photo",
    "to_encoder_input",
]
