"""How fine the baked field must be to reach exact 48+48's error, and where: fields of any k (and of two
k, a finer one in the bricks a surface crosses) scored without storing them.

    python bench/baked_resolution.py [--seeds 1000003 1000011] [--yaws 25 -30] [--resolution 64]
        [--fields 6 8 4/10 ...] [--samples 48 64] [--scenes teacher encoder]

A uniform k = 16 field of a teacher head would take ~770 MiB, beyond lavapipe's 128 MiB storage
binding (a one-level field's points live in one), so it cannot be baked here. Its renders can still be
computed exactly: a field's lookup is the trilinear
mix of its sub-cell's eight corners (``lp3d.render.baked.baked_lookup``), and a corner's value is the
decoder's at that point, rounded to float16 as the field stores it. This script decodes each
sample's corners as the float64 reference renders, for k = 6 (the viewer's field, which this must
match: ``bench/baked_error.py``'s "field" row) and finer, and for *two-level* fields: bricks at
``k_fine`` where ``lp3d.render.baked.needs_fine`` picks them from their k = 4 points (a surface
crosses the brick, or a colour edge lies under one), ``k_coarse`` elsewhere; ``--rule crossed`` is the
rule before the colour edges counted (raw density above ``--dense`` at one point, below ``--solid``
at another). Memory is what such a field would
store (8 bytes a point); PSNR is against exact 192+192 on the GPU, beside exact 48+48's. With
``--samples`` the fields are also rendered with more samples than 48+48 (each lookup costs the same, so
a frame's time grows with the samples): does a finer sampler make up for a coarser field?
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator

import numpy as np

import lp3d_render
from harness import encoder_outputs  # bench/ is on sys.path when run as a script
from lp3d.render.baked import (
    EMPTY_RAW,
    bake_reference,
    colour_weight,
    decode_at,
    field_values,
    needs_fine,
)
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.reference import render_with
from lp3d.render.settings import RenderSettings
from lp3d.render.triplane import TriplaneData
from lp3d.teachers import ProceduralTeacher


def decoded_corners(tri: TriplaneData, q: np.ndarray) -> np.ndarray:
    """(N, 4): the field's values at plane coordinates ``q`` (N, 3) as stored, in float16."""
    return field_values(*decode_at(tri, q)).astype(np.float16).astype(np.float64)


def virtual_lookup(
    tri: TriplaneData, cell_k: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``baked_lookup`` of a field whose cell (i, j, l) is split ``cell_k[i, j, l]`` times per axis (0:
    no brick), its corners decoded on the fly: ``(sigma_raw (...), rgb (..., 3))`` at world
    ``points`` (..., 3)."""
    g = cell_k.shape[0]
    p = points.reshape(-1, 3)
    s = (p * (2.0 / tri.box_warp) + 1.0) * (0.5 * g)
    cell = np.clip(np.floor(s), 0, g - 1)
    k_of = cell_k[tuple(cell.astype(np.int64).T)]
    sigma, rgb = np.full(len(p), EMPTY_RAW), np.zeros((len(p), 3))
    for k in np.unique(k_of[k_of > 0]):
        m = k_of == k
        local = np.clip((s[m] - cell[m]) * k, 0.0, k)
        i0 = np.minimum(np.floor(local), k - 1)
        f = local - i0
        acc, weight = np.zeros((m.sum(), 4)), np.zeros(m.sum())
        for corner in range(8):
            d = np.array([corner & 1, (corner >> 1) & 1, corner >> 2])
            w = np.prod(np.where(d == 1, f, 1.0 - f), axis=-1)
            value = decoded_corners(tri, (cell[m] * k + i0 + d) * (2.0 / (g * k)) - 1.0)
            acc += w[:, None] * value
            weight += w * colour_weight(value[:, 0])
        sigma[m], rgb[m] = acc[:, 0], acc[:, 1:] / weight[:, None]
    return sigma.reshape(points.shape[:-1]), rgb.reshape(*points.shape[:-1], 3)


def scenes(
    seeds: list[int], yaws: list[float], kinds: list[str]
) -> Iterator[tuple[int, float, str, TriplaneData]]:
    """(seed, yaw, what, triplane): each teacher head (kind "teacher"), then (kind "encoder") the
    shipped encoder's triplane of its frontal render (bench/baked.py's scenes)."""
    teacher = ProceduralTeacher(resolution=64)
    if "teacher" in kinds:
        for seed, yaw in zip(seeds, yaws, strict=True):
            yield seed, yaw, "teacher head", teacher.sample(seed)
    if "encoder" not in kinds:
        return
    encoded = encoder_outputs(teacher.sample(seed) for seed in seeds)
    for seed, yaw, tri in zip(seeds, yaws, encoded, strict=True):
        yield seed, yaw, "encoder output of", tri


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[1_000_003, 1_000_011], help="teacher heads")
    p.add_argument("--yaws", type=float, nargs="+", default=[25.0, -30.0], help="one view per head (deg)")
    p.add_argument("--resolution", type=int, default=64, help="rays per side (default 64)")
    p.add_argument(
        "--rule",
        choices=["needs_fine", "crossed"],
        default="needs_fine",
        help="which bricks are fine: the product's rule (default) or density alone (--dense, --solid)",
    )
    p.add_argument("--dense", type=float, default=10.0, help="crossed: raw density rises above this")
    p.add_argument("--solid", type=float, default=50.0, help="... and falls below this (default 50)")
    p.add_argument(
        "--fields",
        nargs="+",
        default=["6", "8", "12", "16", "4/10", "4/12", "4/16"],
        help="fields to score: k (uniform) or k/k_fine (two levels)",
    )
    p.add_argument(
        "--samples", type=int, nargs="+", default=[48], help="the baked renders' S (= N) samples (default 48)"
    )
    p.add_argument(
        "--scenes",
        nargs="+",
        choices=["teacher", "encoder"],
        default=["teacher"],
        help="teacher heads and/or the shipped encoder's triplanes of them (default: teacher)",
    )
    args = p.parse_args(argv)
    if len(args.yaws) != len(args.seeds):
        p.error("give one --yaws per --seeds")
    try:
        levels = [tuple(int(k) for k in f.split("/")) for f in args.fields]
    except ValueError:
        p.error(f"--fields: each is k or k/k_fine, got {args.fields}")
    if any(len(k) > 2 or min(k) < 1 for k in levels):
        p.error(f"--fields: each is k or k/k_fine with k >= 1, got {args.fields}")
    seeds = " ".join(map(str, args.seeds))
    yaws = " ".join(f"{y:g}" for y in args.yaws)
    print(
        f"Command: `python bench/baked_resolution.py --seeds {seeds} --yaws {yaws} "
        f"--resolution {args.resolution} --rule {args.rule}"
        + (f" --dense {args.dense:g} --solid {args.solid:g}" if args.rule == "crossed" else "")
        + " "
        f"--fields {' '.join(args.fields)} --samples {' '.join(map(str, args.samples))}"
        f" --scenes {' '.join(args.scenes)}`\n"
    )
    print(
        "| head, view | field | samples | fine bricks | MiB | points to bake | PSNR vs exact 192+192 "
        "| exact, same samples | exact 48+48 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    r = args.resolution
    for seed, yaw, kind, head in scenes(args.seeds, args.yaws, args.scenes):
        tri = head.to_native()
        index = lp3d_render.bake(tri, subdivisions=2, occupancy_epsilon=1e-4).index
        cam = look_at_camera(yaw_deg=yaw, pitch_deg=5)
        ref = lp3d_render.render(
            tri, cam, resolution=r, depth_resolution=192, depth_resolution_importance=192, outputs=["rgb"]
        )["rgb"]

        def exact_db(n: int, tri: np.ndarray = tri, cam: np.ndarray = cam, ref: np.ndarray = ref) -> float:
            out = lp3d_render.render(
                tri, cam, resolution=r, depth_resolution=n, depth_resolution_importance=n, outputs=["rgb"]
            )
            return psnr_db(out["rgb"], ref)

        exact = {n: exact_db(n) for n in {48, *args.samples}}
        gpu = lp3d_render.render(
            tri, cam, resolution=r, occupancy_epsilon=1e-4, baked_subdivisions=6, outputs=["rgb"]
        )["rgb"]
        view = f"{kind} {seed}, yaw {yaw:g}"
        print(
            f"| {view} | k 6, baked on the GPU | 48+48 | – | | | {psnr_db(gpu, ref):.2f} dB "
            f"| {exact[48]:.2f} dB | {exact[48]:.2f} dB |"
        )
        values = bake_reference(head, index, 4).astype(np.float16)  # the k 4 points as stored
        if args.rule == "needs_fine":
            crossed = needs_fine(values)
        else:
            corners = values[..., 0].reshape(len(values), -1).astype(np.float64)
            crossed = (corners.max(-1) > args.dense) & (corners.min(-1) < args.solid)
        order = np.argsort(index.ravel())
        cells = order[index.ravel()[order] >= 0]  # brick order
        fields = [(f"k {k[0]}", k[0], k[0]) if len(k) == 1 else (f"k {k[0]} / {k[1]}", *k) for k in levels]
        for (name, k_coarse, k_fine), n in ((f, n) for f in fields for n in args.samples):
            cell_k = np.zeros(index.shape, np.int64)
            cell_k.ravel()[cells] = np.where(crossed, k_fine, k_coarse)
            points = np.where(crossed, (k_fine + 1) ** 3, (k_coarse + 1) ** 3).sum()

            def evaluate(
                o: np.ndarray,
                d: np.ndarray,
                t: np.ndarray,
                head: TriplaneData = head,
                cell_k: np.ndarray = cell_k,
            ) -> tuple[np.ndarray, np.ndarray]:
                return virtual_lookup(head, cell_k, o[:, None, :] + t[..., None] * d[:, None, :])

            settings = RenderSettings(resolution=r, depth_resolution=n, depth_resolution_importance=n)
            out = render_with(head, cam, settings, evaluate)["rgb"]
            fine = f"{crossed.sum()} of {len(crossed)}" if k_fine != k_coarse else "–"
            print(
                f"| {view} | {name} | {n}+{n} | {fine} | {points * 8 / 2**20:.0f} | {points / 1e6:.1f} M "
                f"| {psnr_db(out, ref):.2f} dB | {exact[n]:.2f} dB | {exact[48]:.2f} dB |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
