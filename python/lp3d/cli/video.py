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


def _no_frames(path: Path, meta: dict[str, Any]) -> str:
    """The error for a video of which no frame could be decoded."""
    declared = meta.get("frames_declared")
    held = f" of the {declared} the container holds" if declared else ""
    return f"{path}: no frame{held} could be decoded"


def run(args: argparse.Namespace) -> int:
    from lp3d.lift.inference import load_encoder
    from lp3d.photo import (
        DETECT_MAX_SIDE,
        NoFaceError,
        centre_crop,
        crop_image,
        detect_face,
        to_encoder_input,
    )
    from lp3d.photo.video import (
        VIDEO_CROP_SMOOTHING,
        expected_frames,
        nearest_hits,
        read_video,
        smooth_crops,
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
        bar = progress(expected_frames(meta, args.max_frames), "detect")
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
        crops = [crops[j] for j in nearest_hits(np.asarray(hits), len(crops))]
        crops = smooth_crops(crops, VIDEO_CROP_SMOOTHING)

    # Pass 2: crop, encode, smooth the triplane over time, render the new view.
    camera = make_camera(args)[None]
    _, frames = read_video(args.input, args.max_frames)
    start = time.perf_counter()
    t_enc = t_render = 0.0
    state: np.ndarray | None = None
    with Staged() as staged:
        writer = VideoWriter(staged.temp(out_path), out_path.suffix, fps)
        bar = progress(len(crops) if crops else expected_frames(meta, args.max_frames), "video")
        try:
            for i, frame in enumerate(frames):
                crop = crops[min(i, len(crops) - 1)] if crops else centre_crop(frame.shape)
                face = crop_image(frame, crop, pkg.image_size)
                t0 = time.perf_counter()
                planes = encoder.run(to_encoder_input(face[None]))[0]
                t_enc += time.perf_counter() - t0
                state = planes if state is None else args.smooth * state + (1.0 - args.smooth) * planes
                t0 = time.perf_counter()
                image = final_images(native_triplane(pkg.triplane(state)), camera, args, sr, size)[0][0]
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
