"""``lp3d-view``: the viewer's console script. Parses the command line and starts the viewer
compiled into ``lp3d_render`` (the same Rust code as ``cargo run -p lp3d-viewer``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lp3d.cli import parse_samples


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="lp3d-view",
        description="Interactive viewer for EG3D-format triplanes (.npz). Drag to orbit, right-drag or "
        "shift-drag to pan, scroll to zoom, double-click to reset; drop a .npz file to open it.",
    )
    parser.add_argument("triplane", nargs="?", type=Path, help="triplane .npz file")
    parser.add_argument("--screenshot", type=Path, help="render a few frames, save a PNG of the window, exit")
    parser.add_argument("--yaw", type=float, default=0.0, help="initial yaw in degrees (default: 0)")
    parser.add_argument("--pitch", type=float, default=0.0, help="initial pitch in degrees (default: 0)")
    parser.add_argument(
        "--resolution", type=int, default=128, help="rays per side of the final image (default: 128)"
    )
    parser.add_argument(
        "--samples",
        type=parse_samples,
        default=(48, 48),
        metavar="COARSE+FINE",
        help="samples per ray of the final image, EG3D's depth_resolution + depth_resolution_importance "
        "(default: 48+48; 64 alone skips the importance pass)",
    )
    parser.add_argument(
        "--frame-budget-ms",
        type=float,
        default=100.0,
        help="while the camera moves, render at the quality predicted to take at most this per frame; "
        "when it stops, refine to the final quality (default: 100)",
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=3,
        help="UI frames before a screenshot; it also waits for the final quality (default: 3)",
    )
    parser.add_argument(
        "--drag-frames",
        type=int,
        default=0,
        help="with --screenshot: drag the view to orbit over this many UI frames (synthetic pointer "
        "events), then save once the refined image is up; the JSON sidecar records each frame's render "
        "time and quality (default: 0, no drag)",
    )
    args = parser.parse_args(argv)
    if args.screenshot is not None and args.triplane is None:
        parser.error("--screenshot needs a triplane file")
    if args.drag_frames and args.screenshot is None:
        parser.error("--drag-frames needs --screenshot")

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
    except (ValueError, OSError, RuntimeError) as e:
        print(f"lp3d-view: {e}", file=sys.stderr)
        return 1
    if args.screenshot is not None:
        print(f"wrote {args.screenshot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
