"""Reading a photo safely: any Pillow format to (H, W, 3) uint8, with a note for each conversion.

:func:`load_image` applies EXIF orientation and converts grayscale (replicated to 3 channels) and RGBA
(alpha dropped) with a note for each; empty, corrupt, truncated, tiny and huge (> :data:`MAX_PIXELS` or
a side > :data:`MAX_SIDE`) files are rejected clearly; an animated image gives a note that only its
first frame is used. The limits live here and nowhere else.
"""

from __future__ import annotations

import io
import os
import warnings
from pathlib import Path
from typing import BinaryIO

import numpy as np

__all__ = [
    "MAX_PIXELS",
    "PHOTO_SUFFIXES",
    "MAX_SIDE",
    "MIN_SIDE",
    "NoFaceError",
    "PhotoError",
    "decode_image",
    "load_image",
]

# --------------------------------------------------------------------------------------- limits
#: Larger images are rejected (decoding one would need gigabytes).
MAX_PIXELS = 100_000_000
#: Smaller sides are rejected: nothing useful can be cropped from them.
MIN_SIDE = 16
#: Longer sides are rejected: OpenCV's warpAffine (the crop) asserts on sides of 32767 px and more.
MAX_SIDE = 32766
#: File suffixes taken from a folder of photos.
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff")


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


def _pillow_notes(short: str, caught: list[warnings.WarningMessage]) -> list[str]:
    """The notes for the warnings Pillow gave while decoding (others are warned again, as they were)."""
    seen: list[str] = []
    for w in caught:
        text = " ".join(str(w.message).split())
        if f"{os.sep}PIL{os.sep}" not in w.filename:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        elif text not in seen:
            seen.append(text)
    return [f"{short}: damaged metadata ignored ({'; '.join(seen[:2])})"] if seen else []


def load_image(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[str]]:
    """Read an image file as ``(rgb (H, W, 3) uint8, notes)``.

    ``notes`` are human-readable warnings about conversions done (grayscale replicated to RGB, alpha
    dropped, 16-bit reduced, CMYK converted, only the first frame of an animated image used). Raises
    :class:`PhotoError` for a missing path, a folder or other non-regular file, an empty,
    unrecognised, corrupt or truncated file, an image larger than :data:`MAX_PIXELS`, with a side
    above :data:`MAX_SIDE` or below :data:`MIN_SIDE`.
    """
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
    return _decode(p, str(p), p.name)


def decode_image(data: bytes, name: str) -> tuple[np.ndarray, list[str]]:
    """:func:`load_image` of an image held in memory (an upload to ``lp3d serve``), with the same
    checks and limits; ``name`` stands for the file in messages."""
    if not data:
        raise PhotoError(f"{name}: empty file")
    return _decode(io.BytesIO(data), name, name)


def _decode(stream: Path | BinaryIO, label: str, short: str) -> tuple[np.ndarray, list[str]]:
    """:func:`load_image`'s decoding of ``stream``, named ``label`` in errors and ``short`` in notes."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    p, notes = label, []
    try:
        with warnings.catch_warnings(record=True) as caught:
            # Pillow's own warnings (corrupt or truncated EXIF, metadata it skipped) become notes
            # below, once each, instead of raw warning lines on the terminal.
            warnings.simplefilter("always")
            # Our own MAX_PIXELS check replaces Pillow's decompression-bomb warning.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(stream) as im:
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
                        f"{short}: has an alpha channel ({mode}); dropped it (transparent areas keep "
                        "their hidden colour)"
                    )
                    im = im.convert("RGB") if mode in ("RGBA", "RGBa", "PA") else im.convert("L")
                    mode = im.mode
                if mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                    notes.append(f"{short}: {mode} image converted to RGB")
                    im = im.convert("RGB")
                    mode = im.mode
                arr = np.asarray(im)
                frames = _frame_count(source)
                if frames is None:
                    notes.append(f"{short}: unreadable data after the first frame; only the first is used")
                elif frames > 1:
                    notes.append(
                        f"{short}: has {frames} frames (an animated or multi-page {source.format} image); "
                        "only the first is used"
                    )
        notes += _pillow_notes(short, caught)
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
        notes.append(f"{short}: {arr.dtype} pixels ({mode}) reduced to 8 bits")
        arr = _to_uint8(arr)
    if arr.ndim == 2:
        notes.append(f"{short}: grayscale image; replicated to 3 channels")
        arr = np.repeat(arr[:, :, None], 3, axis=2)
    elif arr.ndim != 3 or arr.shape[2] != 3:
        raise PhotoError(f"{p}: unsupported pixel layout {arr.shape} (mode {mode})")
    if min(arr.shape[:2]) < MIN_SIDE:
        raise PhotoError(
            f"{p}: image is {arr.shape[1]}x{arr.shape[0]}, too small (need >= {MIN_SIDE} px a side)"
        )
    return np.ascontiguousarray(arr), notes
