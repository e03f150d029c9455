"""Coarse or fine: how a baked field's samples per ray are best split between EG3D's two passes.

    python bench/baked_samples.py [--splits 48+48 56+48 ...] [--out table.md]

A baked lookup costs the same wherever a sample lies, so a frame's time follows the samples per ray;
which split of them reaches exact 48+48's error soonest? Per scene of bench/baked.py (held-out
teacher heads and the shipped encoder's triplanes of them; its three 128² views), the k 4 / 16 field
(the one that reaches that error) with every skip, rendered at each coarse+fine split and scored
against exact 192+192 (PSNR over RGB in [-1, 1], the mean over the views, as bench/baked.py). A
split at or above exact 48+48's PSNR is marked *. No timing: bench/baked.py times the splits this
picks, beside EG3D. About 3 minutes a scene (mostly the bake).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import lp3d_render
from harness import ALL_SKIPS, PITCH, YAWS, R, bake, scenes  # bench/ is on sys.path when run as a script
from lp3d.cli.common import parse_samples
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db

DEFAULT_SPLITS = (
    "48+48 48+56 56+48 56+56 48+64 64+48 40+64 56+64 64+64 72+72 80+80 64+80 48+80 80+64 "
    "88+64 96+48 96+64 88+88 104+48 104+64 80+96 96+80 96+96 112+64 128+48"
)
#: The field: k 4, k_f 16.
FIELD = (4, 16)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--splits", type=parse_samples, nargs="+", default=[parse_samples(s) for s in DEFAULT_SPLITS.split()]
    )
    p.add_argument("--out", type=Path, help="also write the markdown table here")
    args = p.parse_args(argv)
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=PITCH) for y in YAWS])
    common = {"resolution": R, "outputs": ["rgb"]}

    def mean_psnr(tri: object, ref: np.ndarray, coarse: int, fine: int, **kwargs: object) -> float:
        """The mean PSNR over the views of `tri` rendered at coarse+fine against `ref`."""
        rgb = lp3d_render.render(
            tri, cams, **common, depth_resolution=coarse, depth_resolution_importance=fine, **kwargs
        )["rgb"]
        return statistics.mean(psnr_db(rgb[i], ref[i]) for i in range(len(cams)))

    columns = []  # per scene: (name, exact 48+48's PSNR, each split's PSNR)
    for name, head in scenes():
        print(f"{name} ...", file=sys.stderr, flush=True)
        tri = head.to_native()
        ref = lp3d_render.render(tri, cams, **common, depth_resolution=192, depth_resolution_importance=192)[
            "rgb"
        ]
        target = mean_psnr(tri, ref, 48, 48)
        bake(tri, FIELD)
        lookups = {"baked_subdivisions": FIELD[0], "baked_fine_subdivisions": FIELD[1]} | ALL_SKIPS
        columns.append((name, target, [mean_psnr(tri, ref, c, f, **lookups) for c, f in args.splits]))
    lines = [
        f"Command: `python bench/baked_samples.py` ({time.strftime('%Y-%m-%d')}): k 4 / 16, all skips, "
        "PSNR against exact 192+192 (dB); * at or above exact 48+48's",
        "",
        "| coarse+fine | " + " | ".join(name for name, _, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
        "| exact 48+48 | " + " | ".join(f"{target:.2f}" for _, target, _ in columns) + " |",
    ]
    for i, (c, f) in enumerate(args.splits):
        cells = [f"{dbs[i]:.2f}{' *' if dbs[i] >= target else ''}" for _, target, dbs in columns]
        lines.append(f"| baked {c}+{f} | " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
