"""``lp3d-view``: the viewer's console script. Parses the command line and starts the viewer
compiled into ``lp3d_render`` (the same Rust code as ``cargo run -p lp3d-viewer``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


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
    parser.add_argument("--resolution", type=int, default=128, help="rays per image side (default: 128)")
    parser.add_argument("--frames", type=int, default=3, help="frames before a screenshot (default: 3)")
    args = parser.parse_args(argv)
    if args.screenshot is not None and args.triplane is None:
        parser.error("--screenshot needs a triplane file")

    import lp3d_render

    try:
        lp3d_render.view(
            args.triplane,
            screenshot=args.screenshot,
            yaw=args.yaw,
            pitch=args.pitch,
            resolution=args.resolution,
            frames=args.frames,
        )
    except (ValueError, OSError, RuntimeError) as e:
        print(f"lp3d-view: {e}", file=sys.stderr)
        return 1
    if args.screenshot is not None:
        print(f"wrote {args.screenshot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
