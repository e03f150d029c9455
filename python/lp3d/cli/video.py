"""``lp3d video``: lift a portrait video to a new viewpoint, frame by frame."""

from __future__ import annotations

import argparse
import time
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
    flip_average_arg,
    float_in,
    int_in,
    make_camera,
    native_triplane,
    progress,
    render_args,
    resize_image,
    resolve_model,
    say,
    warn,
)
from lp3d.cli.refining import add_refine_argument, require_torch
from lp3d.lift.steady import MAX_SIGMA, SteadyPlanes

#: ``--steady``'s default width in frames (``bench/video_steadiness.py``; docs/performance.md, "Video").
DEFAULT_STEADY = 2.0

HELP = "lift a portrait video to a new viewpoint, frame by frame"
DESCRIPTION = (
    "For every frame: detect and crop the face, encode it, optionally "
    "smooth the triplane over time, and render it from the given view."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="input video (anything ffmpeg reads)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output video (.mp4 or .gif)")
    p.add_argument(
        "--steady",
        type=float_in(0.0, MAX_SIGMA),
        default=DEFAULT_STEADY,
        metavar="SIGMA",
        help="average each frame's triplane with its neighbours', Gaussian weights of width SIGMA frames "
        f"looking both ways (no lag; default {DEFAULT_STEADY:g}, see docs/performance.md; 0 = off)",
    )
    p.add_argument(
        "--smooth",
        type=float_in(0.0, 1.0, hi_open=True),
        default=0.0,
        help="causal smoothing of the triplane, state = s * state + (1 - s) * new, applied before "
        "--steady (0 = off, default; it lags behind a turning head: prefer --steady)",
    )
    flip_average_arg(p, "each frame")
    add_refine_argument(p, "each frame")
    p.add_argument("--no-detect", action="store_true", help="skip face detection (centre square crop)")
    p.add_argument("--model", type=Path, default=None, help="as for encode")
    p.add_argument("--backend", choices=("onnx", "torch"), default=None, help="as for encode")
    p.add_argument("--max-frames", type=int_in(1, 10**7), default=None, help="stop after this many frames")
    p.add_argument("--fps", type=float_in(0.1, 240.0), default=None, help="output fps (default: the input's)")
    p.add_argument("--side-by-side", action="store_true", help="put the input crop left of the new view")
    camera_args(p, yaw=20.0)
    render_args(p, 128)


def _no_frames(path: Path, meta: dict[str, Any]) -> str:
    """The error for a video of which no frame could be decoded."""
    declared = meta.get("frames_declared")
    held = f" of the {declared} the container holds" if declared else ""
    return f"{path}: no frame{held} could be decoded"


def _lift_frames(
    args: argparse.Namespace,
    encoder: Any,
    crops: list[Any],
    meta: dict[str, Any],
    out_path: Path,
    fps: float,
    size: int,
) -> tuple[int, float, float]:
    """Pass 2 of ``lp3d video``: each frame cropped, encoded, smoothed over time and rendered from the
    new view into ``out_path`` (written whole or not at all). Returns (frames, encode s, render s)."""
    from lp3d.photo import centre_crop, crop_image, to_encoder_input
    from lp3d.photo.video import expected_frames, read_video

    pkg, sr = encoder.package, encoder.superres
    camera = make_camera(args)[None]
    _, frames = read_video(args.input, args.max_frames)
    t_enc = t_render = 0.0
    state: np.ndarray | None = None
    refine_settings = None
    fit_camera: np.ndarray | None = None
    if args.refine > 0:
        from lp3d.lift.refine import RefineSettings, refine

        require_torch()
        refine_settings = RefineSettings(steps=args.refine)
    steady = SteadyPlanes(args.steady)
    with Staged() as staged:
        writer = VideoWriter(staged.temp(out_path), out_path.suffix, fps)
        bar = progress(len(crops) if crops else expected_frames(meta, args.max_frames), "video")

        def write(face: np.ndarray, planes: np.ndarray) -> float:
            """Render one lifted frame from the new view and add it; its render seconds."""
            t0 = time.perf_counter()
            image = final_images(native_triplane(pkg.triplane(planes)), camera, args, sr, size)[0][0]
            seconds = time.perf_counter() - t0
            if args.side_by_side:
                image = np.concatenate([resize_image(face, size), image], axis=1)
            writer.add(image)
            bar.update()
            return seconds

        try:
            for i, frame in enumerate(frames):
                crop = crops[min(i, len(crops) - 1)] if crops else centre_crop(frame.shape)
                face = crop_image(frame, crop, pkg.image_size)
                t0 = time.perf_counter()
                planes = encoder.encode(to_encoder_input(face[None]), flip_average=args.flip_average)[0]
                if refine_settings is not None:  # counted as encoding: both make the frame's planes
                    # The camera is searched for once, then followed from frame to frame.
                    fitted = refine(pkg.triplane(planes), face, refine_settings, start_camera=fit_camera)
                    planes, fit_camera = fitted.triplane.planes, fitted.camera
                t_enc += time.perf_counter() - t0
                state = planes if state is None else args.smooth * state + (1.0 - args.smooth) * planes
                t_render += sum(write(*ready) for ready in steady.push(face, state))
            t_render += sum(write(*ready) for ready in steady.flush())
            if writer.count == 0:
                raise CLIError(_no_frames(args.input, meta))
            writer.close()
        finally:
            writer.abort()
            bar.close()
        staged.commit()
    return writer.count, t_enc, t_render


def run(args: argparse.Namespace) -> int:
    from lp3d.lift.inference import load_encoder
    from lp3d.photo import DETECT_MAX_SIDE
    from lp3d.photo.video import VideoError, expected_frames, face_crops, read_video

    out_path = check_output(args.output, VIDEO_SUFFIXES)
    check_distinct([("input video", args.input)], [("-o", out_path)])
    encoder = load_encoder(resolve_model(args.model), args.backend, superres=not args.raw)
    sr = encoder.superres
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
    if not args.no_detect:
        _, frames = read_video(args.input, args.max_frames)
        bar = progress(expected_frames(meta, args.max_frames), "detect")
        try:
            crops, missing = face_crops(frames, str(args.input), on_frame=bar.update)
        except VideoError:
            raise CLIError(_no_frames(args.input, meta)) from None
        finally:
            bar.close()
        if missing:
            warn(f"no face in {missing} of {len(crops)} frames; using the nearest detection")

    # Pass 2: crop, encode, smooth the triplane over time, render the new view.
    start = time.perf_counter()
    n, t_enc, t_render = _lift_frames(args, encoder, crops, meta, out_path, fps, size)
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
