"""Fixed renders of fixed scenes, to show a change left the renderer's output bit for bit as it was.

    python scripts/render_snapshot.py save before.npz     # with the old build installed
    python scripts/render_snapshot.py save after.npz      # with the new one
    python scripts/render_snapshot.py compare before.npz after.npz

Scenes: the coloured sphere and two procedural-teacher heads, each from three cameras at 64²: exact
mode at 24+24 and 48+48, jittered sampling (seed 7), the skips (occupancy grid, early termination,
empty rays), and a two-level baked field (its values and a render through it). ``compare`` exits 1
and names every array that differs in value or dtype.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def snapshot() -> dict[str, np.ndarray]:
    import lp3d_render
    from lp3d.render.camera import look_at_camera
    from lp3d.render.sample_scenes import coloured_sphere
    from lp3d.teachers.procedural import ProceduralTeacher

    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in ((-30, 5), (0, 0), (25, -10))])
    teacher = ProceduralTeacher()
    scenes = {
        "sphere": coloured_sphere(size=64),
        "teacher0": teacher.sample(0),
        "teacher5": teacher.sample(5),
    }
    skips = {"occupancy_epsilon": 1e-4, "transmittance_threshold": 1e-3, "empty_threshold": 1e-3}
    out: dict[str, np.ndarray] = {}
    for name, tri in scenes.items():
        t = tri.to_native()
        runs = {
            "exact24+24": {"depth_resolution": 24, "depth_resolution_importance": 24},
            "exact48+48": {"depth_resolution": 48, "depth_resolution_importance": 48},
            "jittered": {"deterministic": False, "seed": 7},
            "skips": skips,
        }
        for run, kwargs in runs.items():
            for key, value in lp3d_render.render(t, cams, resolution=64, **kwargs).items():
                out[f"{name}/{run}/{key}"] = value
        field = lp3d_render.bake(t, subdivisions=4, occupancy_epsilon=1e-4, fine_subdivisions=10)
        out[f"{name}/baked/values"] = field.values
        baked = {"baked_subdivisions": 4, "baked_fine_subdivisions": 10, "occupancy_epsilon": 1e-4}
        for key, value in lp3d_render.render(t, cams, resolution=64, outputs=["rgb"], **baked).items():
            out[f"{name}/baked/{key}"] = value
    return out


def compare(a_path: Path, b_path: Path) -> int:
    with np.load(a_path, allow_pickle=False) as a, np.load(b_path, allow_pickle=False) as b:
        if sorted(a.files) != sorted(b.files):
            print(f"the snapshots hold different arrays: {sorted(set(a.files) ^ set(b.files))}")
            return 1
        differ = [
            k for k in a.files if a[k].dtype != b[k].dtype or not np.array_equal(a[k], b[k], equal_nan=True)
        ]
        print(f"{len(a.files)} arrays compared; {len(differ)} differ" + (f": {differ}" if differ else ""))
        return 1 if differ else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("save").add_argument("out", type=Path)
    cmp = sub.add_parser("compare")
    cmp.add_argument("a", type=Path)
    cmp.add_argument("b", type=Path)
    args = p.parse_args(argv)
    if args.command == "compare":
        return compare(args.a, args.b)
    from lp3d.atomic import atomic_path

    arrays = snapshot()
    with atomic_path(args.out) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    print(f"{len(arrays)} arrays written to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
