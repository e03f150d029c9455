"""``lp3d view`` (also the ``lp3d-view`` console script): the interactive viewer compiled into
``lp3d_render`` (the same Rust code as ``cargo run -p lp3d-viewer``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lp3d.cli.common import UsageError, UserError, parse_samples

HELP = "open a triplane file in the interactive viewer"
DESCRIPTION = (
    "Interactive viewer for EG3D-format triplanes (.npz). Drag to orbit, right-drag or shift-drag to pan, "
    "scroll to zoom, double-click to reset; drop a .npz file to open it."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("triplane", nargs="?", type=Path, help="triplane .npz file")
    p.add_argument("--screenshot", type=Path, help="render a few frames, save a PNG of the window, exit")
    p.add_argument("--yaw", type=float, default=0.0, help="initial yaw in degrees (default: 0)")
    p.add_argument("--pitch", type=float, default=0.0, help="initial pitch in degrees (default: 0)")
    p.add_argument(
        "--resolution", type=int, default=128, help="rays per side of the final image (default: 128)"
    )
    p.add_argument(
        "--samples",
        type=parse_samples,
        default=(48, 48),
        metavar="COARSE+FINE",
        help="samples per ray of the final image, EG3D's depth_resolution + depth_resolution_importance "
        "(default: 48+48; 64 alone skips the importance pass)",
    )
    p.add_argument(
        "--frame-budget-ms",
        type=float,
        default=100.0,
        help="while the camera moves, render at the quality predicted to take at most this per frame; "
        "when it stops, refine to the final quality (default: 100)",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=3,
        help="UI frames before a screenshot; it also waits for the final quality (default: 3)",
    )
    p.add_argument(
        "--drag-frames",
        type=int,
        default=0,
        help="with --screenshot: drag the view to orbit over this many UI frames (synthetic pointer "
        "events), then save once the refined image is up; the JSON sidecar records each frame's render "
        "time and quality (default: 0, no drag)",
    )


def run(args: argparse.Namespace) -> int:
    if args.screenshot is not None and args.triplane is None:
        raise UsageError("--screenshot needs a triplane file")
    if args.drag_frames and args.screenshot is None:
        raise UsageError("--drag-frames needs --screenshot")

    import lp3d_render

    try:
        lp3d_render.view(
            args.triplane,
            screenshot=args.screenshot,
            yaw=args.yaw,
            pitch=args.pitch,
            resolution=args.resolution,
            depth_resolution=args.samples[0],
            depth_resolution_importance=args.samples[1],
            frame_budget_ms=args.frame_budget_ms,
            frames=args.frames,
            drag_frames=args.drag_frames,
        )
    except RuntimeError as e:  # the window system or GPU (ValueError and OSError name their input)
        raise UserError(str(e)) from None
    if args.screenshot is not None:
        print(f"wrote {args.screenshot}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``lp3d-view``, the viewer's console script: ``lp3d view`` on its own."""
    import sys

    from lp3d.cli import standalone_parser
    from lp3d.errors import run_command

    return run_command(standalone_parser(sys.modules[__name__], "lp3d-view"), argv)
