"""Contact sheet of the procedural teacher: identities (rows) x yaws (columns), rendered by lp3d_render.

    python -m lp3d.teachers.figure --out docs/teacher.png

Defaults: the default teacher version, seeds 0..7, yaws -45, -22.5, 0, 22.5, 45 degrees (pitch 0,
FFHQ camera), 128^2 rays with 48 + 48 samples (EG3D's FFHQ settings, the viewer's full quality),
RGB mapped from [-1, 1] to [0, 255]. ``--samples 24`` shows the demo's setting; ``--versions 1 2``
stacks the two teachers' sheets (v1 above, v2 below).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

DEFAULT_SEEDS = tuple(range(8))
DEFAULT_YAWS = (-45.0, -22.5, 0.0, 22.5, 45.0)


def render_sheet(
    seeds: Sequence[int] = DEFAULT_SEEDS,
    yaws: Sequence[float] = DEFAULT_YAWS,
    *,
    pitch_deg: float = 0.0,
    resolution: int = 128,
    depth_resolution: int = 48,
    depth_resolution_importance: int = 48,
    version: int | None = None,
) -> np.ndarray:
    """The sheet as (rows * (R + 2) + 2, columns * (R + 2) + 2, 3) uint8: one row per seed, one column
    per yaw, separated by a dark 2-pixel gutter."""
    import lp3d_render
    from lp3d.images import rgb_to_uint8, tile
    from lp3d.render.camera import look_at_camera
    from lp3d.teachers.procedural import ProceduralTeacher

    teacher = ProceduralTeacher() if version is None else ProceduralTeacher(version=version)
    cams = np.stack([look_at_camera(yaw_deg=float(y), pitch_deg=pitch_deg) for y in yaws])
    images = []
    for seed in seeds:
        tri = teacher.sample(int(seed))
        out = lp3d_render.render(
            tri.to_native(),
            cams,
            resolution=resolution,
            depth_resolution=depth_resolution,
            depth_resolution_importance=depth_resolution_importance,
        )
        images.extend(rgb_to_uint8(rgb) for rgb in out["rgb"])
    return tile(images, columns=len(yaws))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m lp3d.teachers.figure", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--out", type=Path, default=Path("docs/teacher.png"), help="PNG to write (%(default)s)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS), help="identities (rows)")
    parser.add_argument("--yaws", type=float, nargs="+", default=list(DEFAULT_YAWS), help="degrees (columns)")
    parser.add_argument("--pitch", type=float, default=0.0, help="camera elevation in degrees")
    parser.add_argument("--resolution", type=int, default=128, help="rays per image side")
    parser.add_argument("--samples", type=int, default=48, help="coarse and fine samples per ray (each)")
    parser.add_argument(
        "--versions",
        type=int,
        nargs="+",
        default=None,
        help="teacher versions, one sheet each, stacked top to bottom (default: the default teacher)",
    )
    args = parser.parse_args(argv)

    from lp3d.images import save_png

    start = time.perf_counter()
    sheets = [
        render_sheet(
            args.seeds,
            args.yaws,
            pitch_deg=args.pitch,
            resolution=args.resolution,
            depth_resolution=args.samples,
            depth_resolution_importance=args.samples,
            version=version,
        )
        for version in (args.versions or [None])
    ]
    gap = np.full((6, sheets[0].shape[1], 3), 255, np.uint8)
    sheet = np.concatenate([x for sh in sheets for x in (sh, gap)][:-1], axis=0)
    path = save_png(args.out, sheet)
    print(
        f"wrote {path}: {len(args.seeds)} identities x {len(args.yaws)} yaws at {args.resolution}^2 "
        f"({time.perf_counter() - start:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
