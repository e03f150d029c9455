"""The occupancy grid and float16 planes on procedural teacher heads: time and error against exact mode.

    python bench/skips.py [--resolution 128] [--samples 48 48] [--repeats 3] [--seeds 0 3]

For each head: the grid's bake time and empty fraction, then ms/frame (median of --repeats after a
warm-up; RGB only, yaw 20° pitch 5°) of exact mode, the occupancy skip (final composite only, the
proved bound of docs/occupancy.md), the skip in the coarse pass too, and exact mode on float16
planes (the head's planes rounded to float16, against float32 planes holding the same values).
Error columns compare with exact mode on float32 planes in the same process.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import replace

import numpy as np

import lp3d_render
from harness import timed  # bench/ is on sys.path when run as a script
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.teachers import ProceduralTeacher

# Time the steady state: the fast kernel, not the quick one the renderer draws with while the fast
# one compiles in the background on a machine whose shader cache lacks it (README, "first render").
os.environ.setdefault("LP3D_KERNEL", "fast")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--samples", type=int, nargs=2, default=[48, 48])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 3])
    parser.add_argument("--epsilons", type=float, nargs="+", default=[1e-4, 1e-3])
    args = parser.parse_args(argv)
    s, n = args.samples
    cam = look_at_camera(yaw_deg=20.0, pitch_deg=5.0)
    kw = {
        "resolution": args.resolution,
        "depth_resolution": s,
        "depth_resolution_importance": n,
        "outputs": ["rgb"],
    }
    info = lp3d_render.adapter_info()
    print(f"Adapter: {info['name']} ({info['driver_info']}); R = {args.resolution}, {s}+{n}, RGB only.\n")
    print("| head | setting | ms/frame | speed-up vs exact | PSNR vs exact | max abs error |")
    print("|---|---|---|---|---|---|")
    for seed in args.seeds:
        t = ProceduralTeacher().sample(seed)
        f32 = t.planes.astype(np.float16).astype(np.float32)  # the same values both ways
        tri = replace(t, planes=f32).to_native()
        half = replace(t, planes=f32.astype(np.float16)).to_native()
        start = time.perf_counter()
        grid = tri.bake_occupancy(64)
        bake_ms = (time.perf_counter() - start) * 1e3
        with_grid = replace(t, planes=f32, occupancy=grid).to_native()
        delta = (t.ray_end - t.ray_start) / (s - 1)
        empty = {e: float((grid <= 1 + math.log(math.expm1(e / delta))).mean()) for e in args.epsilons}
        print(
            f"head {seed}: bake {bake_ms:.0f} ms (G = 64, {t.planes.shape[-1]}² planes); empty cells "
            + ", ".join(f"{100 * v:.0f}% at eps {e:g}" for e, v in empty.items()),
            file=sys.stderr,
        )
        for x in (tri, half, with_grid):
            lp3d_render.render(x, cam, resolution=8)  # upload + compile outside the timings
        exact_ms, exact = timed(lambda tri=tri: lp3d_render.render(tri, cam, **kw), args.repeats)
        rows = [("exact (float32 planes)", exact_ms, exact)]
        ms, out = timed(lambda half=half: lp3d_render.render(half, cam, **kw), args.repeats)
        rows.append(("exact, float16 planes", ms, out))
        for e in args.epsilons:
            for coarse in (False, True):
                ms, out = timed(
                    lambda e=e, coarse=coarse, g=with_grid: lp3d_render.render(
                        g, cam, **kw, occupancy_epsilon=e, occupancy_coarse=coarse
                    ),
                    args.repeats,
                )
                name = f"grid eps {e:g}" + (" + coarse pass" if coarse else " (composite)")
                rows.append((name, ms, out))
        for name, ms, out in rows:
            err = float(np.abs(out["rgb"] - exact["rgb"]).max())
            print(
                f"| teacher seed {seed} | {name} | {ms:,.0f} | {exact_ms / ms:.2f}× | "
                f"{psnr_db(out['rgb'], exact['rgb']):.1f} dB | {err:.1e} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
