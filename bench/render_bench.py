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
import sys

import lp3d_render
from harness import random_triplane, timed  # bench/ is on sys.path when run as a script
from lp3d.render.camera import look_at_camera
from lp3d.render.reference import render_reference

# Time the steady state: the fast kernel, not the quick one the renderer draws with while the fast
# one compiles in the background on a machine whose shader cache lacks it (README, "first render").
os.environ.setdefault("LP3D_KERNEL", "fast")

SAMPLES = [(24, 24), (48, 48), (96, 96)]
RESOLUTIONS = [64, 128]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    args = parser.parse_args(argv)

    data = random_triplane()
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
            wgsl = timed(lambda kw=kw: lp3d_render.render(tri, cam, **kw), args.repeats)[0]
            ref = tw = None
            if r == 64:
                ref = timed(lambda kw=kw: render_reference(data, cam, **kw), 1)[0]
                if render_with_twin is not None:
                    tw = timed(lambda kw=kw: render_with_twin(data, cam, **kw), args.repeats)[0]
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
