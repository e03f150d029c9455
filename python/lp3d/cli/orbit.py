"""``lp3d orbit``: a turntable video (.gif or .mp4) of a triplane file."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from lp3d.cli.common import (
    VIDEO_SUFFIXES,
    CLIError,
    Staged,
    VideoWriter,
    camera_args,
    check_distinct,
    check_output,
    choose_superres,
    describe_size,
    final_images,
    float_in,
    int_in,
    make_camera,
    progress,
    render_args,
    render_triplane_file,
    say,
    superres_model_arg,
)
from lp3d.render.camera import orbit_angles
from lp3d.render.settings import BAKED, BAKED_BOUND_DB, Skips, bake_pays_after

HELP = "render a turntable video (.gif or .mp4)"
DESCRIPTION = (
    "Render a closed camera loop around a triplane: yaw = R sin(2 pi t), pitch = pitch + P cos(2 pi t)."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output video (.gif or .mp4)")
    p.add_argument("--frames", type=int_in(1, 10000), default=36, help="frames in the loop (default: 36)")
    p.add_argument(
        "--yaw-range", type=float_in(0.0, 89.0), default=35.0, help="yaw amplitude in degrees (default: 35)"
    )
    p.add_argument(
        "--pitch-range",
        type=float_in(0.0, 60.0),
        default=0.0,
        help="pitch amplitude in degrees (default: 0)",
    )
    p.add_argument("--fps", type=float_in(0.1, 120.0), default=18.0, help="frames per second (default: 18)")
    p.add_argument("--batch", type=int_in(1, 64), default=4, help="frames per render call (default: 4)")
    camera_args(p, yaw=None)
    render_args(p, 128)
    superres_model_arg(p)
    p.add_argument(
        "--baked",
        nargs="?",
        const="on",
        default="off",
        choices=("auto", "on", "off"),
        help="decode the field once and render every frame by lookups (docs/baked.md): several times "
        "faster after a short bake, but adds error against exact mode (measured in "
        "docs/performance.md). RGB only, so with --raw. '--baked' "
        "alone: always; 'auto': when the orbit has enough frames for the bake to pay and its first "
        "frame baked is within --baked-bound of the exact one; 'off' (default): exact frames, which "
        "keep exact 48+48's error",
    )
    p.add_argument(
        "--baked-bound",
        type=float_in(10.0, 120.0),
        default=BAKED_BOUND_DB,
        metavar="DB",
        help=f"--baked auto's least PSNR of the first baked frame against the exact one "
        f"(default: {BAKED_BOUND_DB:g} dB)",
    )


def bake_for(args: argparse.Namespace, rtri: object, sr: object) -> Skips:
    """Bake ``rtri``'s field for ``args``' samples before the first frame (saying how long it took);
    the skips that render with it."""
    import lp3d_render

    if sr is not None:
        raise CLIError(
            "--baked: the baked field holds RGB, and the super-resolution network reads all 32 features; "
            "add --raw (or drop --baked)"
        )
    start = time.perf_counter()
    bar = progress(None, "bake", unit="point")
    shown = [0]

    def advance(done: int, total: int) -> None:
        if hasattr(bar, "total"):
            bar.total = total
        bar.update(done - shown[0])
        shown[0] = done

    try:
        field = lp3d_render.bake(
            rtri,
            subdivisions=BAKED.baked_subdivisions,
            fine_subdivisions=BAKED.baked_fine_subdivisions,
            occupancy_epsilon=BAKED.occupancy_epsilon,
            depth_resolution=args.samples[0],
            progress=advance,
        )
    except ValueError as e:
        raise CLIError(f"{args.triplane}: --baked: {e}") from None
    finally:
        bar.close()
    say(
        f"baked the field in {time.perf_counter() - start:.1f} s ({field.bricks} bricks, "
        f"{field.device_bytes / 2**20:.0f} MiB)"
    )
    return BAKED


def auto_baked(args: argparse.Namespace, rtri: object, sr: object, cams: np.ndarray, size: int) -> Skips:
    """``--baked auto``: the baked field's skips when it can serve the orbit (no super-resolution),
    the orbit is long enough for the bake to pay (:func:`~lp3d.render.settings.bake_pays_after`) and
    its first frame is within ``--baked-bound`` dB of the exact one; else exact (the default skips).
    Says which, and why."""
    from lp3d.render.psnr import psnr_db

    if sr is not None:
        say("exact frames: the super-resolution network reads all 32 features, the baked field RGB (--raw)")
        return Skips()
    pays_after = bake_pays_after(*args.samples)
    if len(cams) < pays_after:
        say(f"exact frames: {len(cams)} are fewer than a bake pays for ({pays_after}; --baked bakes anyway)")
        return Skips()

    def first_frame(skips: Skips) -> np.ndarray:
        args.skips = skips
        return final_images(rtri, cams[:1], args, sr, size, path=args.triplane)[1]["rgb"]

    exact = first_frame(Skips())
    baked = bake_for(args, rtri, sr)
    score = psnr_db(first_frame(baked), exact)
    if score >= args.baked_bound:
        say(f"baked frames: the first is {score:.1f} dB from the exact one (bound {args.baked_bound:g} dB)")
        return baked
    say(
        f"exact frames: the first baked frame is {score:.1f} dB from the exact one, below the bound "
        f"({args.baked_bound:g} dB; --baked-bound to change it)"
    )
    return Skips()


def run(args: argparse.Namespace) -> int:
    out_path = check_output(args.output, VIDEO_SUFFIXES)
    if not (-90.0 < args.pitch - args.pitch_range and args.pitch + args.pitch_range < 90.0):
        raise CLIError(
            f"--pitch {args.pitch:g} with --pitch-range {args.pitch_range:g} leaves (-90, 90) degrees"
        )
    check_distinct([("triplane", args.triplane)], [("-o", out_path)])
    tri, rtri = render_triplane_file(args.triplane)
    sr, how = choose_superres(args, tri)
    size = args.resolution or (sr.output_resolution if sr is not None else 128)
    angles = orbit_angles(args.frames, args.yaw_range, args.pitch_range)
    cams = np.stack([make_camera(args, yaw=y, pitch=args.pitch + p) for y, p in angles])
    say(f"orbit: {len(cams)} frames of {describe_size(sr, size)}; {how}")
    if args.baked == "on":
        args.skips = bake_for(args, rtri, sr)
    elif args.baked == "auto":
        args.skips = auto_baked(args, rtri, sr, cams, size)

    start = time.perf_counter()
    with Staged() as staged:
        writer = VideoWriter(staged.temp(out_path), out_path.suffix, args.fps)
        bar = progress(len(cams), "orbit")
        try:
            for i in range(0, len(cams), args.batch):
                frames, _ = final_images(rtri, cams[i : i + args.batch], args, sr, size, path=args.triplane)
                for frame in frames:
                    writer.add(frame)
                bar.update(len(frames))
            writer.close()
        finally:
            writer.abort()
            bar.close()
        staged.commit()
    seconds = time.perf_counter() - start
    say(
        f"rendered {len(cams)} frames at {size}² in {seconds:.1f} s "
        f"({seconds / len(cams):.2f} s/frame); wrote {out_path}"
    )
    return 0
