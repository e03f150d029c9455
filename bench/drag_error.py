"""How far each frame `lp3d-view` can draw while dragging is from the exact image, as the viewer
shows it: rendered at its rung's resolution, scaled to 128² with bilinear filtering, against exact
192+192 at 128².

    python bench/drag_error.py [--scene encoder] [--figure docs/viewer-drag-rungs.png]   # ~6 minutes

The rungs are those of a 128² · 48+48 view (`crates/viewer/src/quality.rs`): the exact ladder's
drag rungs, and the baked fields' with the viewer's skips (`crates/viewer/src/bake.rs`: epsilon
1e-4, transmittance and empty-ray thresholds 1e-3, the occupancy grid in the coarse pass; each
field baked for half the chosen samples, as the viewer bakes it): the quick field (k 4 / 10) at
the rung's samples and the fine one (k 4 / 16) with a third more coarse samples. Scenes: the viewer
bench's teacher head (seed 0) and two held-out ones (`--scene teacher`), or the shipped encoder's
triplanes of frontal renders of them (`--scene encoder`, what `lp3d demo` makes and a user opens);
three novel views each (yaw -30/0/30, pitch 5).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

import lp3d_render
from harness import (  # bench/ is on sys.path when run as a script
    FINE_FIELD,
    QUICK_FIELD,
    VIEWER_SKIPS,
    encoder_output,
)
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.settings import BAKED
from lp3d.teachers import ProceduralTeacher

os.environ.setdefault("LP3D_KERNEL", "fast")

SEEDS = (0, 1_000_003, 1_000_011)
YAWS = (-30.0, 0.0, 30.0)
PITCH = 5.0
R = 128
QUICK, FINE = QUICK_FIELD, FINE_FIELD
#: (label, resolution, coarse samples, fine samples, field or None for exact).
RUNGS = [
    ("exact 128² · 48+48 (the still frame)", 128, 48, 48, None),
    ("fine field, baked 128² · 64+48 (drag rung)", 128, 64, 48, FINE),
    ("fine field, baked 128² · 48+24 (baked-only rung 36+24)", 128, 48, 24, FINE),
    ("fine field, baked 128² · 32+24 (baked-only rung 24+24)", 128, 32, 24, FINE),
    ("quick field, baked 128² · 48+48", 128, 48, 48, QUICK),
    ("quick field, baked 128² · 36+24 (baked-only rung)", 128, 36, 24, QUICK),
    ("quick field, baked 128² · 24+24 (baked-only rung)", 128, 24, 24, QUICK),
    ("quick field, baked 64² · 48+48", 64, 48, 48, QUICK),
    ("exact 64² · 48+48", 64, 48, 48, None),
    ("exact 64² · 12+12", 64, 12, 12, None),
    ("exact 32² · 12+12", 32, 12, 12, None),
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


def render(
    tri, cams: np.ndarray, res: int, coarse: int, fine: int, field: tuple[int, int] | None
) -> np.ndarray:
    """The rung's frame; from `field` (baked on `tri` already) unless None."""
    baked = {} if field is None else {"baked_subdivisions": field[0], "baked_fine_subdivisions": field[1]}
    return lp3d_render.render(
        tri,
        cams,
        resolution=res,
        depth_resolution=coarse,
        depth_resolution_importance=fine,
        outputs=["rgb"],
        **(VIEWER_SKIPS | baked if field else {}),
    )["rgb"]


def scene(seed: int, kind: str) -> object:
    """Teacher head `seed`, or the shipped encoder's triplane of a frontal render of it."""
    head = ProceduralTeacher().sample(seed)
    return (head if kind == "teacher" else encoder_output(head)).to_native()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--figure", type=Path, help="write the rungs of the first scene's yaw 30° view here (PNG, 2× zoom)"
    )
    p.add_argument("--scene", choices=("teacher", "encoder"), default="teacher")
    args = p.parse_args(argv)
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=PITCH) for y in YAWS])
    psnr: dict[str, list[float]] = {name: [] for name, *_ in RUNGS}
    figure: list[np.ndarray] = []
    for seed in SEEDS:
        tri = scene(seed, args.scene)
        ref = render(tri, cams, R, 192, 192, None)
        images: dict[str, np.ndarray] = {}
        # One field on the triplane at a time: each rung of a field right after its bake.
        for field in (None, FINE, QUICK):
            if field is not None:
                lp3d_render.bake(
                    tri,
                    subdivisions=field[0],
                    fine_subdivisions=field[1],
                    occupancy_epsilon=BAKED.occupancy_epsilon,
                    depth_resolution=24,
                )
            for name, res, coarse, fine, rung_field in RUNGS:
                if rung_field == field:
                    images[name] = shown(render(tri, cams, res, coarse, fine, field))
        for name, *_ in RUNGS:
            img = images[name]
            scores = [psnr_db(img[i], ref[i]) for i in range(len(cams))]
            psnr[name].append(float(np.mean(scores)))
            print(f"  head {seed}: {name}: {psnr[name][-1]:.2f} dB", file=sys.stderr, flush=True)
            if seed == SEEDS[0]:
                figure.append(img[-1])
        if seed == SEEDS[0]:
            figure.append(ref[-1])
    heads = ", ".join(map(str, SEEDS))
    print(
        f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; "
        f"{args.scene} scenes of heads {heads}"
    )
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
