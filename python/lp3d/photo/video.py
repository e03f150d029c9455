"""Videos in: frames read by the bundled ffmpeg, and per-frame crops steadied over time.

:func:`read_video` validates the file (size limits as for photos, :mod:`lp3d.photo.load`) and yields
(H, W, 3) uint8 frames; :func:`count_video_frames` counts the container's frames without decoding.
Faces are detected per frame (:func:`lp3d.photo.detect_face`); frames without one borrow the nearest
detection (:func:`nearest_hits`) and :func:`smooth_crops` damps the landmarks' frame-to-frame jitter.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.photo.framing import Crop
from lp3d.photo.load import MAX_PIXELS, MAX_SIDE, NoFaceError, PhotoError
from lp3d.photo.prepare import detect_face

__all__ = [
    "VIDEO_CROP_SMOOTHING",
    "face_crops",
    "VIDEO_SCAN_TIMEOUT_S",
    "VideoError",
    "count_video_frames",
    "expected_frames",
    "nearest_hits",
    "read_video",
    "smooth_crops",
]


class VideoError(PhotoError):
    """A video that cannot be used; the message names the file and what is wrong."""


#: Crop smoothing in ``lp3d video`` (exponential, per frame): damps the landmarks' frame-to-frame jitter.
VIDEO_CROP_SMOOTHING = 0.6


def _ffmpeg_reason(e: Exception) -> str:
    """The informative last line of an imageio-ffmpeg error (its message embeds ffmpeg's whole log)."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    tail = [ln for ln in lines if "rror" in ln or "nvalid" in ln or "No such" in ln]
    return (tail[-1] if tail else lines[0] if lines else type(e).__name__)[:300]


#: Longest time ffmpeg may take to scan a video's packets (no decoding: seconds even for long films).
VIDEO_SCAN_TIMEOUT_S = 600.0


def count_video_frames(path: Path) -> int | None:
    """Frames the container holds in its first video stream: its packets, counted by the bundled ffmpeg
    without decoding (so a damaged frame still counts). ``None`` when ffmpeg cannot copy the stream (the
    decoder may still read it). Raises :class:`VideoError` for a file with no video stream (audio only,
    an empty container), whose ffmpeg error would only say "Invalid argument"."""
    import re
    import subprocess

    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", "-i", str(path)]
    cmd += ["-map", "0:v:0", "-c", "copy", "-f", "null", "-"]
    try:
        done = subprocess.run(cmd, capture_output=True, timeout=VIDEO_SCAN_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise VideoError(
            f"{path}: ffmpeg took more than {VIDEO_SCAN_TIMEOUT_S:g} s to scan the video"
        ) from None
    log = done.stderr.decode(errors="replace")
    if "matches no streams" in log:
        what = "an audio stream but no video" if re.search(r"Stream #\S+: Audio:", log) else "no video stream"
        raise VideoError(f"{path}: has {what}")
    counts = re.findall(r"frame=\s*(\d+)", log)
    return int(counts[-1]) if done.returncode == 0 and counts else None


def read_video(path: Path, max_frames: int | None) -> tuple[dict[str, Any], Iterator[np.ndarray]]:
    """(metadata, frames (H, W, 3) uint8) of a video file read by the bundled ffmpeg; ``max_frames=0``
    only reads the metadata, and adds ``frames_declared`` (:func:`count_video_frames`).

    The decoder skips frames it cannot decode (ffmpeg goes on after a damaged frame), so callers
    compare the frames they got with ``frames_declared``: ``lp3d video`` warns, naming both counts.
    """
    if not path.exists():
        raise VideoError(f"{path}: no such file")
    if path.is_dir():
        raise VideoError(f"{path}: is a folder, not a video")
    if not path.is_file():
        raise VideoError(f"{path}: is not a regular file")
    if path.stat().st_size == 0:
        raise VideoError(f"{path}: empty file")
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise VideoError(f"reading videos needs imageio-ffmpeg: {e}") from None
    declared = count_video_frames(path) if max_frames == 0 else None
    if declared == 0:
        raise VideoError(f"{path}: the video stream has no frames")
    try:
        gen = imageio_ffmpeg.read_frames(str(path))
        meta = next(gen)
        w, h = (int(v) for v in meta["size"])
    # imageio-ffmpeg parses ffmpeg's log: besides OSError, an odd log gives Index/Attribute/ValueError.
    except (OSError, RuntimeError, StopIteration, IndexError, AttributeError, ValueError, KeyError) as e:
        raise VideoError(f"{path}: cannot read as a video ({_ffmpeg_reason(e)})") from None
    if not (0 < w * h <= MAX_PIXELS and max(w, h) <= MAX_SIDE):
        gen.close()
        raise VideoError(
            f"{path}: frames are {w}x{h}; need 1 to {MAX_PIXELS / 1e6:.0f} MP and sides up to {MAX_SIDE} px"
        )
    if max_frames == 0:  # a probe: metadata only, stop ffmpeg now
        gen.close()
        return {**meta, "frames_declared": declared}, iter(())

    def frames() -> Iterator[np.ndarray]:
        try:
            for i, raw in enumerate(gen):
                if max_frames is not None and i >= max_frames:
                    break
                yield np.frombuffer(raw, np.uint8).reshape(h, w, 3)
        except (OSError, RuntimeError) as e:
            raise VideoError(f"{path}: error while decoding ({_ffmpeg_reason(e)})") from None
        finally:
            gen.close()

    return meta, frames()


def expected_frames(meta: dict[str, Any], max_frames: int | None) -> int | None:
    """Frames to expect (for the progress bar): the container's count, else ffmpeg's duration times fps,
    capped by --max-frames."""
    n = meta.get("frames_declared")
    if n is None:
        try:
            n = round(float(meta["duration"]) * float(meta["fps"]))
        except (KeyError, TypeError, ValueError, OverflowError):
            return max_frames
    n = n if n > 0 else None
    return n if max_frames is None else min(max_frames, n or max_frames)


def nearest_hits(hits: np.ndarray, n: int) -> np.ndarray:
    """For each of ``n`` frames, the index in sorted ``hits`` (frames with a face) nearest to it."""
    frames = np.arange(n)
    right = np.clip(np.searchsorted(hits, frames), 0, len(hits) - 1)
    left = np.clip(right - 1, 0, len(hits) - 1)
    use_left = np.abs(hits[left] - frames) <= np.abs(hits[right] - frames)
    return np.where(use_left, hits[left], hits[right])


def smooth_crops(crops: list[Crop], alpha: float) -> list[Crop]:
    """Exponential smoothing of the crop parameters, run forward then backward (no lag)."""
    if alpha <= 0 or len(crops) < 2:
        return crops
    keys = ("cx", "cy", "side", "angle_deg")
    vals = np.array([[getattr(c, k) for k in keys] for c in crops], np.float64)
    for i in range(1, len(vals)):
        vals[i] = alpha * vals[i - 1] + (1 - alpha) * vals[i]
    for i in range(len(vals) - 2, -1, -1):
        vals[i] = alpha * vals[i + 1] + (1 - alpha) * vals[i]
    return [
        replace(c, **dict(zip(keys, map(float, v), strict=True))) for c, v in zip(crops, vals, strict=True)
    ]


def face_crops(
    frames: Iterable[np.ndarray],
    name: str,
    *,
    smoothing: float = VIDEO_CROP_SMOOTHING,
    on_frame: Callable[[], object] | None = None,
) -> tuple[list[Crop], int]:
    """``(crop per frame, frames without a face)``: the face found in each frame (:func:`detect_face`),
    frames without one taking the nearest detection, then :func:`smooth_crops`. ``on_frame`` is called
    after each frame (a progress bar). Raises :class:`VideoError` when no frame decodes and
    :class:`NoFaceError` when no frame has a face; ``name`` (the file) leads both messages."""
    found: list[Crop | None] = []
    for frame in frames:
        face = detect_face(frame)
        found.append(None if face is None else face.crop)
        if on_frame is not None:
            on_frame()
    if not found:
        raise VideoError(f"{name}: no frame could be decoded")
    hits = [i for i, c in enumerate(found) if c is not None]
    if not hits:
        raise NoFaceError(
            f"{name}: no face found in any frame; for a centred portrait video pass --no-detect"
        )
    crops = [found[j] for j in nearest_hits(np.asarray(hits), len(found))]
    return smooth_crops(crops, smoothing), len(found) - len(hits)  # type: ignore[arg-type]
