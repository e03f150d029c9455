"""``lp3d video``: lift a portrait video to a new viewpoint, frame by frame."""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.cli.common import (
    VIDEO_SUFFIXES,
    CLIError,
    Staged,
    VideoWriter,
    camera_args,
    check_distinct,
    check_output,
    describe_size,
    final_images,
    float_in,
    int_in,
    make_camera,
    progress,
    render_args,
    render_triplane,
    resize_image,
    resolve_model,
    say,
    warn,
)

HELP = "lift a portrait video to a new viewpoint, frame by frame"
DESCRIPTION = (
    "For every frame: detect and crop the face, encode it, optionally "
    "smooth the triplane over time, and render it from the given view."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="input video (anything ffmpeg reads)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output video (.mp4 or .gif)")
    p.add_argument(
        "--smooth",
        type=float_in(0.0, 1.0, hi_open=True),
        default=0.0,
        help="temporal smoothing of the triplane, state = s * state + (1 - s) * new "
        "(0 = off, default; 0.5 is moderate)",
    )
    p.add_argument("--no-detect", action="store_true", help="skip face detection (centre square crop)")
    p.add_argument("--model", type=Path, default=None, help="as for encode")
    p.add_argument("--backend", choices=("onnx", "torch"), default=None, help="as for encode")
    p.add_argument("--max-frames", type=int_in(1, 10**7), default=None, help="stop after this many frames")
    p.add_argument("--fps", type=float_in(0.1, 240.0), default=None, help="output fps (default: the input's)")
    p.add_argument("--side-by-side", action="store_true", help="put the input crop left of the new view")
    camera_args(p, yaw=20.0)
    render_args(p, 128)


#: Crop smoothing in ``lp3d video`` (exponential, per frame): damps the Haar box's frame-to-frame jitter.
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
    decoder may still read it). Raises :class:`CLIError` for a file with no video stream (audio only,
    an empty container), whose ffmpeg error would only say "Invalid argument"."""
    import re
    import subprocess

    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", "-i", str(path)]
    cmd += ["-map", "0:v:0", "-c", "copy", "-f", "null", "-"]
    try:
        done = subprocess.run(cmd, capture_output=True, timeout=VIDEO_SCAN_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise CLIError(
            f"{path}: ffmpeg took more than {VIDEO_SCAN_TIMEOUT_S:g} s to scan the video"
        ) from None
    log = done.stderr.decode(errors="replace")
    if "matches no streams" in log:
        what = "an audio stream but no video" if re.search(r"Stream #\S+: Audio:", log) else "no video stream"
        raise CLIError(f"{path}: has {what}")
    counts = re.findall(r"frame=\s*(\d+)", log)
    return int(counts[-1]) if done.returncode == 0 and counts else None


def read_video(path: Path, max_frames: int | None) -> tuple[dict[str, Any], Iterator[np.ndarray]]:
    """(metadata, frames (H, W, 3) uint8) of a video file read by the bundled ffmpeg; ``max_frames=0``
    only reads the metadata, and adds ``frames_declared`` (:func:`count_video_frames`).

    The decoder skips frames it cannot decode (ffmpeg goes on after a damaged frame), so callers
    compare the frames they got with ``frames_declared``: :func:`run` warns, naming both counts.
    """
    from lp3d.photo import MAX_PIXELS, MAX_SIDE

    if not path.exists():
        raise CLIError(f"{path}: no such file")
    if path.is_dir():
        raise CLIError(f"{path}: is a folder, not a video")
    if not path.is_file():
        raise CLIError(f"{path}: is not a regular file")
    if path.stat().st_size == 0:
        raise CLIError(f"{path}: empty file")
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise CLIError(f"reading videos needs imageio-ffmpeg: {e}") from None
    declared = count_video_frames(path) if max_frames == 0 else None
    if declared == 0:
        raise CLIError(f"{path}: the video stream has no frames")
    try:
        gen = imageio_ffmpeg.read_frames(str(path))
        meta = next(gen)
        w, h = (int(v) for v in meta["size"])
    # imageio-ffmpeg parses ffmpeg's log: besides OSError, an odd log gives Index/Attribute/ValueError.
    except (OSError, RuntimeError, StopIteration, IndexError, AttributeError, ValueError, KeyError) as e:
        raise CLIError(f"{path}: cannot read as a video ({_ffmpeg_reason(e)})") from None
    if not (0 < w * h <= MAX_PIXELS and max(w, h) <= MAX_SIDE):
        gen.close()
        raise CLIError(
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
            raise CLIError(f"{path}: error while decoding ({_ffmpeg_reason(e)})") from None
        finally:
            gen.close()

    return meta, frames()


def _frame_estimate(meta: dict[str, Any], max_frames: int | None) -> int | None:
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


def _no_frames(path: Path, meta: dict[str, Any]) -> str:
    """The error for a video of which no frame could be decoded."""
    declared = meta.get("frames_declared")
    held = f" of the {declared} the container holds" if declared else ""
    return f"{path}: no frame{held} could be decoded"


def _nearest(hits: np.ndarray, n: int) -> np.ndarray:
    """For each of ``n`` frames, the index in sorted ``hits`` (frames with a face) nearest to it."""
    frames = np.arange(n)
    right = np.clip(np.searchsorted(hits, frames), 0, len(hits) - 1)
    left = np.clip(right - 1, 0, len(hits) - 1)
    use_left = np.abs(hits[left] - frames) <= np.abs(hits[right] - frames)
    return np.where(use_left, hits[left], hits[right])


def _smooth_crops(crops: list[Any], alpha: float) -> list[Any]:
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


def run(args: argparse.Namespace) -> int:
    from lp3d.inference import load_encoder
    from lp3d.photo import (
        DETECT_MAX_SIDE,
        NoFaceError,
        centre_crop,
        crop_image,
        detect_face,
        to_encoder_input,
    )

    out_path = check_output(args.output, VIDEO_SUFFIXES)
    check_distinct([("input video", args.input)], [("-o", out_path)])
    encoder = load_encoder(resolve_model(args.model), args.backend, superres=not args.raw)
    pkg, sr = encoder.package, encoder.superres
    size = args.resolution or (sr.output_resolution if sr is not None else 128)
    meta, _ = read_video(args.input, 0)  # fail fast on an unreadable file
    fps = float(args.fps or meta.get("fps") or 25.0)
    w, h = meta["size"]
    if args.raw:
        how = "raw volume render (--raw)"
    elif sr is not None:
        how = f"super-resolved by {sr.description}"
    else:
        how = "raw volume render (the model has no super-resolution network)"
    say(f"video: {args.input} {w}x{h} at {fps:g} fps; model {encoder.description}")
    say(f"frames: {describe_size(sr, size)}; {how}")
    if max(w, h) > 4 * DETECT_MAX_SIDE:
        warn(f"{w}x{h} frames are large; detection runs on downscaled copies")

    # Pass 1: where the face is in each frame (gaps filled from the nearest detection, then smoothed).
    crops: list[Any] = []
    if args.no_detect:
        crops = []
    else:
        _, frames = read_video(args.input, args.max_frames)
        bar = progress(_frame_estimate(meta, args.max_frames), "detect")
        try:
            for frame in frames:
                found = detect_face(frame)
                crops.append(None if found is None else found.crop)
                bar.update()
        finally:
            bar.close()
        if not crops:
            raise CLIError(_no_frames(args.input, meta))
        hits = [i for i, c in enumerate(crops) if c is not None]
        if not hits:
            raise NoFaceError(
                f"{args.input}: no face found in any frame; for a centred portrait video pass --no-detect"
            )
        if len(hits) < len(crops):
            warn(f"no face in {len(crops) - len(hits)} of {len(crops)} frames; using the nearest detection")
        crops = [crops[j] for j in _nearest(np.asarray(hits), len(crops))]
        crops = _smooth_crops(crops, VIDEO_CROP_SMOOTHING)

    # Pass 2: crop, encode, smooth the triplane over time, render the new view.
    camera = make_camera(args)[None]
    _, frames = read_video(args.input, args.max_frames)
    start = time.perf_counter()
    t_enc = t_render = 0.0
    state: np.ndarray | None = None
    with Staged() as staged:
        writer = VideoWriter(staged.temp(out_path), out_path.suffix, fps)
        bar = progress(len(crops) if crops else _frame_estimate(meta, args.max_frames), "video")
        try:
            for i, frame in enumerate(frames):
                crop = crops[min(i, len(crops) - 1)] if crops else centre_crop(frame.shape)
                face = crop_image(frame, crop, pkg.image_size)
                t0 = time.perf_counter()
                planes = encoder.run(to_encoder_input(face[None]))[0]
                t_enc += time.perf_counter() - t0
                state = planes if state is None else args.smooth * state + (1.0 - args.smooth) * planes
                t0 = time.perf_counter()
                image = final_images(render_triplane(pkg.triplane(state)), camera, args, sr, size)[0][0]
                t_render += time.perf_counter() - t0
                if args.side_by_side:
                    image = np.concatenate([resize_image(face, size), image], axis=1)
                writer.add(image)
                bar.update()
            if writer.count == 0:
                raise CLIError(_no_frames(args.input, meta))
            writer.close()
        finally:
            writer.abort()
            bar.close()
        staged.commit()
    n = writer.count
    declared = meta["frames_declared"]
    expected = declared if declared is None or args.max_frames is None else min(declared, args.max_frames)
    if expected is not None and n < expected:
        # A damaged file: ffmpeg skipped frames it could not decode. Warn rather than fail, so a long
        # video with one bad frame still lifts, but never silently.
        warn(
            f"{args.input}: decoded {n} of the {expected} frames the container holds (damaged frames are "
            f"skipped); the output has {n} frames"
        )
    total = time.perf_counter() - start
    say(
        f"lifted {n} frames in {total:.1f} s (encode {t_enc / n:.3f} s/frame, render {t_render / n:.3f} "
        f"s/frame at {size}²); wrote {out_path}"
    )
    return 0
