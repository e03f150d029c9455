"""Exact mode against EG3D's own renderer: same head, camera and settings, one process.

    EG3D_SRC=/path/to/eg3d/eg3d python bench/eg3d_speed.py [--resolution 128] [--samples 48] [--repeats 3]

EG3D is not a dependency: point ``EG3D_SRC`` at the ``eg3d/`` folder of NVlabs/eg3d (the one holding
``training/`` and ``torch_utils/``). Without it the script says so and exits 0, so anyone can run it.

EG3D side: its unmodified ``ImportanceRenderer``, ``RaySampler`` and ``OSGDecoder`` (the decoder's
``FullyConnectedLayer`` weights set so that its effective weights are the head's), float32, CPU,
``torch.set_num_threads(--threads)``. Its two random draws (the coarse jitter's ``rand_like`` and
``sample_pdf(det=False)``) are switched to lp3d's deterministic mode (no jitter, ``det=True``) from
outside, so the two renders can be compared as well as timed. lp3d side: ``lp3d_render.render`` with
every output (rgb, features, depth, weights), its pipeline compiled by an untimed warm-up; with
``--outputs rgb`` only the RGB image and depth, what an RGB view needs (lp3d's decoder then computes
density and three colour channels; EG3D's always computes all 32 features, whose first three are
the RGB image, so the two are compared on those).

The scene: ``--scene random`` (default), ``harness.random_triplane()``, a 256² random triplane with an
EG3D-scaled decoder, or ``--scene teacher``, a procedural teacher head (its decoder's gains of up to
4000 turn float32 rounding in the plane fetch into feature differences of ~1e-2, so only its timing
and depth compare). The two renderers' frames are timed in pairs, back to back (each first in turn),
so that a slow spell of the machine falls on both. Reported: median seconds per frame of each, the
ratio of the medians and the lowest and highest ratio within a pair, and the largest
differences in features and depth.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import lp3d_render
from harness import eg3d_renderer, random_triplane  # bench/ is on sys.path when run as a script
from lp3d.render.camera import look_at_camera
from lp3d.teachers import ProceduralTeacher

# Time the steady state: the fast kernel, not the quick one the renderer draws with while the fast
# one compiles in the background on a machine whose shader cache lacks it (README, "first render").
os.environ.setdefault("LP3D_KERNEL", "fast")


def interleaved_s(
    a: Callable[[], object], b: Callable[[], object], repeats: int
) -> list[tuple[float, float]]:
    """Seconds of `a` and of `b` for each repeat, the two run back to back (in turn first), so that a
    slow spell of the machine slows both of a pair rather than one renderer's whole series."""
    pairs = []
    for i in range(repeats):
        times = [0.0, 0.0]
        for k in (0, 1) if i % 2 == 0 else (1, 0):
            start = time.perf_counter()
            (a, b)[k]()
            times[k] = time.perf_counter() - start
        pairs.append((times[0], times[1]))
    return pairs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=128, help="rays per side (default 128)")
    p.add_argument("--samples", type=int, default=48, help="coarse and importance samples each (default 48)")
    p.add_argument("--repeats", type=int, default=3, help="timed frames per renderer (default 3)")
    p.add_argument("--threads", type=int, default=2, help="torch threads for EG3D (default 2)")
    p.add_argument(
        "--scene", choices=("random", "teacher"), default="random", help="what to render (default random)"
    )
    p.add_argument("--seed", type=int, default=0, help="teacher identity for --scene teacher (default 0)")
    p.add_argument(
        "--outputs",
        choices=("all", "rgb"),
        default="all",
        help="what lp3d_render computes: every output (default) or the RGB image and depth only",
    )
    args = p.parse_args(argv)
    for name in ("resolution", "samples", "repeats", "threads"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1")
    src = os.environ.get("EG3D_SRC")
    if not src:
        print(
            "EG3D_SRC is not set: skipping the comparison with EG3D's renderer "
            "(point it at NVlabs/eg3d's eg3d/ folder to run it)."
        )
        return 0
    import torch

    torch.set_num_threads(args.threads)
    head = ProceduralTeacher().sample(args.seed) if args.scene == "teacher" else random_triplane()
    w0, b0, w1, b1 = head.w0, head.b0, head.w1, head.b1
    renderer, rays, decoder = eg3d_renderer(Path(src), w0, b0, w1, b1)
    camera = look_at_camera(yaw_deg=20.0, pitch_deg=5.0)
    r, s = args.resolution, args.samples
    options = {
        "ray_start": head.ray_start,
        "ray_end": head.ray_end,
        "box_warp": head.box_warp,
        "depth_resolution": s,
        "depth_resolution_importance": s,
        "disparity_space_sampling": False,
        "clamp_mode": "softplus",
        "white_back": False,
    }
    planes = torch.from_numpy(head.planes).unsqueeze(0)
    cam = torch.from_numpy(np.asarray(camera, np.float32)).unsqueeze(0)

    def eg3d() -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            origins, directions = rays(cam[:, :16].view(-1, 4, 4), cam[:, 16:25].view(-1, 3, 3), r)
            features, depth, _ = renderer(planes, decoder, origins, directions, options)
        return features, depth

    tri = head.to_native()

    outputs = None if args.outputs == "all" else ["rgb", "depth"]

    def lp3d() -> dict[str, np.ndarray]:
        return lp3d_render.render(
            tri, camera, resolution=r, depth_resolution=s, depth_resolution_importance=s, outputs=outputs
        )

    ours = lp3d()  # compiles the pipeline (untimed)
    theirs = eg3d()
    pairs = interleaved_s(lp3d, eg3d, args.repeats)
    t_lp3d = statistics.median(p[0] for p in pairs)
    t_eg3d = statistics.median(p[1] for p in pairs)
    pair_ratios = sorted(e / m for m, e in pairs)
    feat = theirs[0][0].numpy().reshape(r, r, -1)
    depth = theirs[1][0].numpy().reshape(r, r)
    mine = ours["features"] if outputs is None else ours["rgb"]  # lp3d: (C, R, R)
    d_feat = float(np.abs(mine.transpose(1, 2, 0) - feat[..., : mine.shape[0]]).max())
    d_depth = float(np.abs(ours["depth"].reshape(r, r) - depth).max())

    info = lp3d_render.adapter_info()
    print(
        f"Command: `EG3D_SRC=... python bench/eg3d_speed.py --scene {args.scene} --resolution {r} "
        f"--samples {s} --repeats {args.repeats} --threads {args.threads} --outputs {args.outputs}`  "
    )
    print(
        f"{platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}; "
        f"adapter {info.get('name')} ({info.get('driver_info', '')}); "
        f"torch {torch.__version__}, {args.threads} threads\n"
    )
    print(
        "| R | samples | lp3d outputs | EG3D ImportanceRenderer s/frame | lp3d_render s/frame | EG3D / lp3d "
        "| per pair, lowest–highest "
        f"| max abs Δ {'features' if outputs is None else 'RGB (features 0-2)'} | max abs Δ depth |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    ratio = t_eg3d / t_lp3d
    print(
        f"| {r} | {s}+{s} | {args.outputs} | {t_eg3d:.2f} | {t_lp3d:.2f} | {ratio:.2f}× "
        f"| {pair_ratios[0]:.2f}–{pair_ratios[-1]:.2f}× | {d_feat:.1e} | {d_depth:.1e} |"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
