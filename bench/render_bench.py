"""Baseline render timings: lp3d_render (WGSL) against the float64 NumPy reference and the torch twin.

    python bench/render_bench.py [--repeats 3] [--markdown]

Prints ms/frame (median of --repeats after a warm-up that compiles the pipeline) for R in {64, 128}
and samples in {24+24, 48+48, 96+96}, on a 256x256 random triplane seen from the frontal FFHQ camera.
The NumPy reference (and the torch twin, when torch is installed) run at R=64 in the same process,
so the ratios compare like with like on one machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.reference import render_reference
from lp3d.render.triplane import TriplaneData

# Time the steady state: the fast kernel, not the quick one the renderer draws with while the fast
# one compiles in the background on a machine whose shader cache lacks it (README, "first render").
os.environ.setdefault("LP3D_KERNEL", "fast")

SAMPLES = [(24, 24), (48, 48), (96, 96)]
RESOLUTIONS = [64, 128]


def scene() -> TriplaneData:
    rng = np.random.default_rng(0)
    return TriplaneData(
        planes=rng.standard_normal((3, 32, 256, 256)).astype(np.float32),
        w0=(rng.standard_normal((64, 32)) / np.sqrt(32)).astype(np.float32),
        b0=(0.1 * rng.standard_normal(64)).astype(np.float32),
        w1=(rng.standard_normal((33, 64)) / 8).astype(np.float32),
        b1=(0.1 * rng.standard_normal(33)).astype(np.float32),
    )


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    args = parser.parse_args(argv)

    data = scene()
    tri = data.to_native()
    cam = look_at_camera()
    info = lp3d_render.adapter_info()
    lp3d_render.render(tri, cam, resolution=8)  # compile the pipeline outside the timings

    try:
        import torch

        from lp3d.render.torch_twin import render_with_twin

        torch_threads = torch.get_num_threads()
    except ImportError:
        render_with_twin = None
        torch_threads = 0

    rows = []
    for r in RESOLUTIONS:
        for s, n in SAMPLES:
            kw = {"resolution": r, "depth_resolution": s, "depth_resolution_importance": n}
            wgsl = median_ms(lambda kw=kw: lp3d_render.render(tri, cam, **kw), args.repeats)
            ref = tw = None
            if r == 64:
                ref = median_ms(lambda kw=kw: render_reference(data, cam, **kw), 1)
                if render_with_twin is not None:
                    tw = median_ms(lambda kw=kw: render_with_twin(data, cam, **kw), args.repeats)
            rows.append((r, f"{s}+{n}", wgsl, ref, tw))
            print(f"R={r:4d} {s}+{n}: lp3d_render {wgsl:9.1f} ms", file=sys.stderr)

    fmt = lambda v: "—" if v is None else f"{v:,.1f}"  # noqa: E731
    ratio = lambda a, b: "—" if a is None or b is None else f"{a / b:.2f}×"  # noqa: E731
    header = (
        f"adapter: {info['name']} ({info['backend']}, {info['device_type']}, {info['driver_info']}); "
        f"host: {platform.processor() or platform.machine()}, torch threads: {torch_threads}"
    )
    if args.markdown:
        print(header + "\n")
        print(
            "| R | samples | lp3d_render ms/frame | NumPy float64 ms/frame | torch twin ms/frame | "
            "torch / lp3d_render |"
        )
        print("|---|---|---|---|---|---|")
        for r, smp, w, ref, tw in rows:
            print(f"| {r} | {smp} | {fmt(w)} | {fmt(ref)} | {fmt(tw)} | {ratio(tw, w)} |")
    else:
        print(header)
        for r, smp, w, ref, tw in rows:
            print(
                f"R={r:4d} {smp:>6}: lp3d_render {fmt(w):>10} ms  "
                f"numpy {fmt(ref):>10} ms  torch {fmt(tw):>10} ms"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
