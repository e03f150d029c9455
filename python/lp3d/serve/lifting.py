"""What ``lp3d serve`` does with an image, without any web framework: a photo or a webcam frame read
from bytes with the photo loader's checks and limits, aligned, encoded, and its planes packed for the
page.

* :meth:`Lifter.photo`: an uploaded photo, as ``lp3d encode`` lifts it (:func:`lp3d.photo.prepare_photo`).
* :meth:`Lifter.align_frame` then :meth:`Lifter.encode`: one webcam frame of a live session. Each
  frame's face is found and aligned as a photo's (:func:`lp3d.photo.detect_face`); frames without a
  face keep the session's last crop
  (a centred square before the first face); the crops are steadied as ``lp3d video`` steadies them
  (:data:`lp3d.photo.video.VIDEO_CROP_SMOOTHING`), but causally, since a live frame cannot wait for
  the frames after it (:class:`LiveSession`).
* :func:`triplane_message`: planes and a JSON header as the page reads them (one binary message, the
  same for a photo's answer and a live frame's).
"""

from __future__ import annotations

import io
import json
import struct
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from lp3d.lift.loaded import LoadedEncoder
from lp3d.photo import (
    MAX_PIXELS,
    MAX_SIDE,
    MIN_SIDE,
    Crop,
    PhotoError,
    centre_crop,
    crop_image,
    decode_image,
    detect_face,
    prepare_photo,
    to_encoder_input,
)
from lp3d.photo.video import VIDEO_CROP_SMOOTHING
from lp3d.render.triplane import TriplaneData

__all__ = [
    "MAX_FRAME_BYTES",
    "MAX_FRAME_PIXELS",
    "MAX_UPLOAD_BYTES",
    "MESSAGE_MAGIC",
    "PHOTO_LIMITS",
    "LiveSession",
    "Lifter",
    "PhotoResult",
    "frame_id_and_image",
    "triplane_message",
]

#: Largest photo upload, in bytes (its pixels are capped by the photo loader, :data:`MAX_PIXELS`).
MAX_UPLOAD_BYTES = 40 << 20
#: Largest live frame message (a 4-byte frame number, then one JPEG or PNG frame), in bytes.
MAX_FRAME_BYTES = 2 << 20
#: Largest live frame, in pixels: a webcam frame, not a photo (a small JPEG of a huge flat image would
#: otherwise cost a photo's decode on every frame).
MAX_FRAME_PIXELS = 4096 * 2304
#: First four bytes of every triplane message.
MESSAGE_MAGIC = b"LP3T"


@dataclass
class PhotoResult:
    """A lifted photo: its ``triplane`` (float16 planes: what the page draws is what the ``.npz``
    holds), the aligned ``crop`` (S, S, 3) uint8, its ``pose`` (yaw, pitch) or None (no detection), and
    what the page shows about it."""

    triplane: TriplaneData
    crop: np.ndarray
    pose: tuple[float, float] | None
    name: str
    description: str
    notes: list[str]
    timings_ms: dict[str, float]


@dataclass
class LiveSession:
    """One live stream's state: the last (steadied) crop and how many frames had no face. Frames of one
    session are aligned one at a time (:attr:`lock`), in the order they arrive."""

    crop: Crop | None = None
    frames: int = 0
    no_face: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def steady(self, found: Crop | None, shape: tuple[int, ...]) -> Crop:
        """The crop of the next frame: the face's, blended with the last one as ``lp3d video``'s forward
        pass blends them, or the last one again when no face was found."""
        self.frames += 1
        if found is None:
            self.no_face += 1
            if self.crop is None:
                return centre_crop(shape)
            return self.crop
        if self.crop is None:
            self.crop = found
            return found
        a = VIDEO_CROP_SMOOTHING
        keys = ("cx", "cy", "side", "angle_deg")
        blended = {k: a * getattr(self.crop, k) + (1 - a) * getattr(found, k) for k in keys}
        self.crop = replace(found, **blended)
        return self.crop


def _ms(t0: float) -> float:
    return round((time.perf_counter() - t0) * 1000.0, 2)


def frame_id_and_image(message: bytes) -> tuple[int, bytes]:
    """A live frame message's (frame number, image bytes): a little-endian u32, then the image."""
    if len(message) < 5:
        raise PhotoError("live frame: a message is a 4-byte frame number followed by an image")
    return struct.unpack_from("<I", message)[0], message[4:]


def _frame_size(data: bytes) -> tuple[int, int] | None:
    """The (width, height) an image's header declares, read without decoding it; None when Pillow
    cannot read the header (the decoder then says why)."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            return im.size
    except Exception:  # any failure here is reported by decode_image, with its message
        return None


class Lifter:
    """The server's one encoder (shared by every client; ONNX Runtime sessions may run from several
    threads at once) and the steps around it."""

    def __init__(self, encoder: LoadedEncoder) -> None:
        self.encoder = encoder
        self.package = encoder.package
        self.size = self.package.image_size
        # One encode at a time: ONNX Runtime already spreads one over every core, and two at once
        # would fight for them while the other worker thread aligns the next frame.
        self._encoding = threading.Lock()

    def warm_up(self) -> None:
        """Load and run once what the first frame would otherwise wait for: the face detector, the
        pose search's tables and the encoder's session."""
        from lp3d.photo import FACE_TEMPLATE, align_face

        detect_face(np.zeros((MIN_SIDE * 4, MIN_SIDE * 4, 3), np.uint8))
        align_face(FACE_TEMPLATE[:, :2] * np.array([-400.0, -400.0]) + 100.0)
        self.encode(np.zeros((self.size, self.size, 3), np.uint8))

    def encode(self, face: np.ndarray) -> np.ndarray:
        """Planes (3, 32, T, T) float16 of one aligned face (S, S, 3) uint8. Planes the decoder would
        take past float32, or past float16's range, are refused (ValueError)."""
        with self._encoding:
            planes = self.encoder.encode(to_encoder_input(face[None]), flip_average=False)[0]
        self.package.triplane(planes)  # the package's range checks
        half = planes.astype(np.float16)
        if not np.isfinite(half).all():
            raise ValueError("the encoder's planes exceed float16's range")
        return half

    def photo(self, data: bytes, name: str, *, detect: bool) -> PhotoResult:
        """Lift an uploaded photo (raises :class:`PhotoError` with a one-line message for a file that is
        not an image, too large, or without a usable face)."""
        t0 = time.perf_counter()
        rgb, notes = decode_image(data, name)
        t_read = _ms(t0)
        t0 = time.perf_counter()
        prep = prepare_photo(rgb, self.size, detect=detect, name=name)
        t_align = _ms(t0)
        t0 = time.perf_counter()
        planes = self.encode(prep.image)
        t_encode = _ms(t0)
        camera = None
        if prep.pose is not None:
            from lp3d.render.camera import look_at_camera

            camera = look_at_camera(yaw_deg=prep.pose[0], pitch_deg=prep.pose[1])
        source = f"lp3d serve {name} (model {self.package.config_name}, {self.encoder.backend})"
        tri = self.package.triplane(planes, source=source[:200], camera=camera)
        return PhotoResult(
            triplane=tri,
            crop=prep.image,
            pose=prep.pose,
            name=name,
            description=prep.description,
            notes=notes,
            timings_ms={"read": t_read, "align": t_align, "encode": t_encode},
        )

    def align_frame(
        self, data: bytes, session: LiveSession, *, detect: bool = True
    ) -> tuple[np.ndarray, dict]:
        """One live frame read (photo loader's checks, :data:`MAX_FRAME_PIXELS`), its face found and
        its crop steadied: ``(face (S, S, 3) uint8, info)``."""
        t0 = time.perf_counter()
        size = _frame_size(data)
        if size is not None and size[0] * size[1] > MAX_FRAME_PIXELS:
            w, h = size
            raise PhotoError(f"live frame: {w}x{h} is larger than a webcam frame ({MAX_FRAME_PIXELS} pixels)")
        rgb, _ = decode_image(data, "live frame")
        t_read = _ms(t0)
        t0 = time.perf_counter()
        found = detect_face(rgb) if detect else None
        alignment = None if found is None else found.alignment
        with session.lock:
            crop = session.steady(None if alignment is None else alignment.crop, rgb.shape)
        face = crop_image(rgb, crop, self.size)
        info = {
            "face": alignment is not None,
            "pose": None if alignment is None else [alignment.yaw_deg, alignment.pitch_deg],
            "timings_ms": {"read": t_read, "align": _ms(t0)},
        }
        return face, info


def triplane_message(planes: np.ndarray, header: dict[str, Any]) -> bytes:
    """The page's binary message of ``planes`` (3, 32, H, W) float16: :data:`MESSAGE_MAGIC`, the
    header's length (u32, little-endian), the header as JSON (padded with spaces to 4 bytes), then
    the planes channel-last (3, H, W, 32) little-endian float16 (``lp3d.share.plane_texels``' layout)."""
    _, c, h, w = planes.shape
    head = {**header, "height": h, "width": w, "dtype": "float16"}
    text = json.dumps(head, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")
    text += b" " * (-(len(MESSAGE_MAGIC) + 4 + len(text)) % 4)
    texels = np.ascontiguousarray(planes.transpose(0, 2, 3, 1), dtype="<f2").tobytes()
    return MESSAGE_MAGIC + struct.pack("<I", len(text)) + text + texels


#: The photo loader's pixel limits, as the page states them.
PHOTO_LIMITS = {"max_pixels": MAX_PIXELS, "max_side": MAX_SIDE, "max_bytes": MAX_UPLOAD_BYTES}
