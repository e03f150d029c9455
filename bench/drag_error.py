"""How far each frame `lp3d-view` can draw while dragging is from the exact image, as the viewer
shows it: rendered at its rung's resolution, scaled to 128² with bilinear filtering, against exact
192+192 at 128².

    python bench/drag_error.py [--figure docs/viewer-drag-rungs.png]      # about 2 minutes

The rungs are those of a 128² · 48+48 view (`crates/viewer/src/quality.rs`): the exact ladder's
drag rungs, and the baked field's with the viewer's skips (`crates/viewer/src/bake.rs`: k 4 / 10,
epsilon 1e-4, transmittance and empty-ray thresholds 1e-3, the occupancy grid in the coarse pass;
the field baked for half the chosen samples, as the viewer bakes it). Scenes: the viewer bench's
teacher head (seed 0) and two held-out ones, three novel views each (yaw -30/0/30, pitch 5).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.settings import BAKED
from lp3d.teachers import ProceduralTeacher

os.environ.setdefault("LP3D_KERNEL", "fast")

SEEDS = (0, 1_000_003, 1_000_011)
YAWS = (-30.0, 0.0, 30.0)
PITCH = 5.0
R = 128
#: The viewer's baked-frame skips (crates/viewer/src/bake.rs, `baked_settings`).
VIEWER_SKIPS = {
    "occupancy_epsilon": BAKED.occupancy_epsilon,
    "occupancy_coarse": True,
    "transmittance_threshold": 1e-3,
    "empty_threshold": 1e-3,
    "baked_subdivisions": BAKED.baked_subdivisions,
    "baked_fine_subdivisions": BAKED.baked_fine_subdivisions,
}
#: (label, resolution, samples per pass, baked).
RUNGS = [
    ("exact 128² · 48+48 (the still frame)", 128, 48, False),
    ("baked 128² · 48+48", 128, 48, True),
    ("baked 128² · 24+24 (baked-only rung)", 128, 24, True),
    ("baked 64² · 48+48", 64, 48, True),
    ("exact 64² · 48+48", 64, 48, False),
    ("exact 64² · 12+12", 64, 12, False),
    ("exact 32² · 12+12", 32, 12, False),
]


def shown(rgb: np.ndarray) -> np.ndarray:
    """(N, 3, r, r) -> (N, 3, R, R): the texture's bilinear magnification (pixel centres, clamped)."""
    r = rgb.shape[-1]
    if r == R:
        return rgb
    x = (np.arange(R) + 0.5) * r / R - 0.5
    i0 = np.clip(np.floor(x).astype(int), 0, r - 1)
    i1 = np.clip(i0 + 1, 0, r - 1)
    f = np.clip(x - np.floor(x), 0.0, 1.0)
    f = np.where(x < 0, 0.0, f)
    rows = rgb[:, :, i0] * (1 - f)[:, None] + rgb[:, :, i1] * f[:, None]
    return rows[..., i0] * (1 - f) + rows[..., i1] * f


def render(tri, cams: np.ndarray, res: int, samples: int, baked: bool) -> np.ndarray:
    return lp3d_render.render(
        tri,
        cams,
        resolution=res,
        depth_resolution=samples,
        depth_resolution_importance=samples,
        outputs=["rgb"],
        **(VIEWER_SKIPS if baked else {}),
    )["rgb"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--figure", type=Path, help="write the rungs of the first scene's yaw 30° view here (PNG, 2× zoom)"
    )
    args = p.parse_args(argv)
    teacher = ProceduralTeacher()
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=PITCH) for y in YAWS])
    psnr: dict[str, list[float]] = {name: [] for name, *_ in RUNGS}
    figure: list[np.ndarray] = []
    for seed in SEEDS:
        tri = teacher.sample(seed).to_native()
        ref = render(tri, cams, R, 192, False)
        lp3d_render.bake(
            tri,
            subdivisions=BAKED.baked_subdivisions,
            fine_subdivisions=BAKED.baked_fine_subdivisions,
            occupancy_epsilon=BAKED.occupancy_epsilon,
            depth_resolution=24,
        )
        for name, res, samples, baked in RUNGS:
            img = shown(render(tri, cams, res, samples, baked))
            scores = [psnr_db(img[i], ref[i]) for i in range(len(cams))]
            psnr[name].append(float(np.mean(scores)))
            print(f"  head {seed}: {name}: {psnr[name][-1]:.2f} dB", file=sys.stderr, flush=True)
            if seed == SEEDS[0]:
                figure.append(img[-1])
        if seed == SEEDS[0]:
            figure.append(ref[-1])
    heads = ", ".join(map(str, SEEDS))
    print(f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; heads {heads}")
    print()
    print("| frame (shown at 128²) | " + " | ".join(f"head {s}" for s in SEEDS) + " |")
    print("|---|" + "---|" * len(SEEDS))
    for name, values in psnr.items():
        print(f"| {name} | " + " | ".join(f"{v:.2f} dB" for v in values) + " |")
    if args.figure:
        from lp3d.images import rgb_to_uint8, save_png, tile

        # Each pixel drawn 2 × 2, so the rungs' differences are visible at a glance.
        images = [rgb_to_uint8(im).repeat(2, axis=0).repeat(2, axis=1) for im in figure]
        save_png(args.figure, tile(images, columns=len(images)))
        names = ", ".join(n for n, *_ in RUNGS)
        print(f"\nwrote {args.figure}: {names}, exact 192+192 (head {SEEDS[0]}, yaw 30°)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
