"""Photos in: safe image loading, face detection, alignment and the crop the encoder was trained on.

The encoder only works on images framed like its training data (the teacher's frontal renders), so a
photo is detected, levelled and cropped to that framing before encoding:

1. :func:`load_image` reads any Pillow format into (H, W, 3) uint8, applying EXIF orientation and
   converting grayscale (replicated to 3 channels) and RGBA (alpha dropped) with a note for each;
   empty, corrupt, truncated, tiny and huge (> :data:`MAX_PIXELS` or a side > :data:`MAX_SIDE`) files
   are rejected clearly; an animated image gives a note that only its first frame is used.
2. :func:`detect_face` finds the largest frontal face with OpenCV's bundled Haar cascades on a copy
   downscaled to at most :data:`DETECT_MAX_SIDE`, then the two eyes inside it for the roll angle.
3. :func:`crop_for_face` turns the face box into a square :class:`Crop` with the framing constants
   below; :func:`crop_image` resamples it (rotated so the eyes are level) to the encoder's size.

The framing constants live here and nowhere else.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = [
    "DETECT_MAX_SIDE",
    "FACE_BOX_CENTER_OFFSET_Y",
    "FACE_BOX_WIDTH_FRACTION",
    "IMAGE_SUFFIXES",
    "MAX_PIXELS",
    "MAX_SIDE",
    "MIN_SIDE",
    "Crop",
    "FaceDetection",
    "NoFaceError",
    "PhotoError",
    "centre_crop",
    "crop_for_face",
    "crop_image",
    "detect_face",
    "load_image",
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

# --------------------------------------------------------------------------------------- limits
#: Larger images are rejected (decoding one would need gigabytes).
MAX_PIXELS = 100_000_000
#: Smaller sides are rejected: nothing useful can be cropped from them.
MIN_SIDE = 16
#: Longer sides are rejected: OpenCV's warpAffine (the crop) asserts on sides of 32767 px and more.
MAX_SIDE = 32766
#: Detection runs on a copy whose longer side is at most this (Haar cascades need no more, and
#: a 100 MP photo would take minutes at full size).
DETECT_MAX_SIDE = 1024
#: File suffixes taken from a folder of photos.
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff")


class PhotoError(ValueError):
    """An image that cannot be used; the message names the file and what is wrong."""


class NoFaceError(PhotoError):
    """No face was found (the message suggests ``--no-detect``)."""


# --------------------------------------------------------------------------------------- loading


def _to_uint8(arr: np.ndarray) -> np.ndarray:
    """Integer or float pixel data of any depth -> uint8 (16-bit and float images are rescaled)."""
    if arr.dtype == np.uint8:
        return arr
    if arr.dtype == np.bool_:
        return arr.astype(np.uint8) * 255
    a = arr.astype(np.float64)
    if arr.dtype.kind == "f":
        a = np.nan_to_num(a)
        peak = 1.0 if a.max(initial=0.0) <= 1.0 else 255.0
    else:
        peak = 65535.0 if a.max(initial=0.0) > 255 else 255.0
    return np.clip(np.round(a * (255.0 / peak)), 0, 255).astype(np.uint8)


def _frame_count(im: object) -> int | None:
    """Frames in an opened Pillow image (animated GIF/PNG/WebP, multi-page TIFF): 1 for a still
    image, ``None`` when the data after the first frame is too damaged to count them (the first
    frame, the one used, has already been decoded)."""
    # Counting seeks through the later frames, where Pillow's parsers raise whatever a damaged file
    # provokes (IndexError, struct.error, ...). The frame in use is already decoded, so any failure
    # here only changes the note.
    try:
        if not getattr(im, "is_animated", False):
            return 1
        return int(getattr(im, "n_frames", 2))
    except Exception:
        return None


def load_image(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[str]]:
    """Read an image file as ``(rgb (H, W, 3) uint8, notes)``.

    ``notes`` are human-readable warnings about conversions done (grayscale replicated to RGB, alpha
    dropped, 16-bit reduced, CMYK converted, only the first frame of an animated image used). Raises
    :class:`PhotoError` for a missing path, a folder or other non-regular file, an empty,
    unrecognised, corrupt or truncated file, an image larger than :data:`MAX_PIXELS`, with a side
    above :data:`MAX_SIDE` or below :data:`MIN_SIDE`.
    """
    from PIL import Image, ImageOps, UnidentifiedImageError

    p = Path(path)
    if not p.exists():
        raise PhotoError(f"{p}: no such file")
    if p.is_dir():
        raise PhotoError(f"{p}: is a folder, not an image")
    if not p.is_file():  # a FIFO or a device would block the reader or never end
        raise PhotoError(f"{p}: is not a regular file")
    try:
        size = p.stat().st_size
    except OSError as e:
        raise PhotoError(f"{p}: cannot read ({e.strerror or e})") from None
    if size == 0:
        raise PhotoError(f"{p}: empty file")
    notes: list[str] = []
    try:
        with warnings.catch_warnings():
            # Our own MAX_PIXELS check replaces Pillow's decompression-bomb warning.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(p) as im:
                source = im
                w, h = im.size
                if w * h > MAX_PIXELS:
                    raise PhotoError(
                        f"{p}: image is {w}x{h} = {w * h / 1e6:.0f} MP, more than the "
                        f"{MAX_PIXELS / 1e6:.0f} MP limit; downscale it first"
                    )
                if max(w, h) > MAX_SIDE:
                    raise PhotoError(f"{p}: image is {w}x{h}, a side over {MAX_SIDE} px; downscale it first")
                im.load()
                im = ImageOps.exif_transpose(im)
                mode = im.mode
                if mode == "P":
                    im = im.convert("RGBA" if "transparency" in im.info else "RGB")
                    mode = im.mode
                if mode in ("RGBA", "RGBa", "LA", "La", "PA"):
                    notes.append(
                        f"{p.name}: has an alpha channel ({mode}); dropped it (transparent areas keep "
                        "their hidden colour)"
                    )
                    im = im.convert("RGB") if mode in ("RGBA", "RGBa", "PA") else im.convert("L")
                    mode = im.mode
                if mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                    notes.append(f"{p.name}: {mode} image converted to RGB")
                    im = im.convert("RGB")
                    mode = im.mode
                arr = np.asarray(im)
                frames = _frame_count(source)
                if frames is None:
                    notes.append(f"{p.name}: unreadable data after the first frame; only the first is used")
                elif frames > 1:
                    notes.append(
                        f"{p.name}: has {frames} frames (an animated or multi-page {source.format} image); "
                        "only the first is used"
                    )
    except Image.DecompressionBombError as e:
        raise PhotoError(f"{p}: image too large ({e})") from None
    except UnidentifiedImageError:
        raise PhotoError(f"{p}: not an image file (or a format Pillow cannot read)") from None
    except PhotoError:
        raise
    except (OSError, SyntaxError, ValueError, EOFError) as e:
        # Pillow reports truncated/corrupt data as OSError ("image file is truncated"), SyntaxError, ...
        raise PhotoError(f"{p}: corrupt or truncated image ({e})") from None
    if arr.dtype != np.uint8:
        notes.append(f"{p.name}: {arr.dtype} pixels ({mode}) reduced to 8 bits")
        arr = _to_uint8(arr)
    if arr.ndim == 2:
        notes.append(f"{p.name}: grayscale image; replicated to 3 channels")
        arr = np.repeat(arr[:, :, None], 3, axis=2)
    elif arr.ndim != 3 or arr.shape[2] != 3:
        raise PhotoError(f"{p}: unsupported pixel layout {arr.shape} (mode {mode})")
    if min(arr.shape[:2]) < MIN_SIDE:
        raise PhotoError(
            f"{p}: image is {arr.shape[1]}x{arr.shape[0]}, too small (need >= {MIN_SIDE} px a side)"
        )
    return np.ascontiguousarray(arr), notes


# ------------------------------------------------------------------------------------ detection


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


# ------------------------------------------------------------------------------------- cropping


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
