"""The baked field (docs/baked.md) against exact mode and EG3D's own renderer: run time against error.

    EG3D_SRC=/path/to/eg3d/eg3d python bench/baked.py [--out bench/baked.md] [--plot bench/baked.png]

Scenes: procedural teacher heads of held-out identities, and what the shipped encoder makes of a
frontal render of each. Per scene, three novel views (yaw -30, 0, 30; pitch 5) at 128², each setting
timed as the median of ``--repeats`` calls rendering the three views (RGB only, the fast kernel warmed
up first) and scored against exact 192+192 (PSNR over RGB in [-1, 1], as bench/pareto.py). The bake
is timed once per field and reported with its bricks and device memory; "frames to amortise" is the
bake time over the time a frame saves against exact 48+48. With ``EG3D_SRC`` (NVlabs/eg3d's
``eg3d/`` folder) EG3D's unmodified ``ImportanceRenderer`` renders the same views at 48+48 in the
same process (bench/eg3d_speed.py's set-up), and every row gets its speed-up over it; without it
that column says so.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import re
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import lp3d_render
from harness import (  # bench/ is on sys.path when run as a script
    ALL_SKIPS,
    EPS,
    PITCH,
    SKIP,
    YAWS,
    R,
    bake,
    eg3d_renderer,
    scenes,
    timed,
)
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.triplane import TriplaneData

os.environ.setdefault("LP3D_KERNEL", "fast")

#: A baked setting's skips, by the suffix of its name.
BAKED_SKIPS = {
    "": {},
    ", T + empty skips": {"transmittance_threshold": SKIP, "empty_threshold": SKIP},
    ", all skips": {"occupancy_coarse": True, "transmittance_threshold": SKIP, "empty_threshold": SKIP},
}


@dataclass(frozen=True)
class Setting:
    name: str
    #: (coarse, fine) samples per ray: EG3D's depth_resolution and depth_resolution_importance.
    samples: tuple[int, int]
    kwargs: dict


SETTINGS = [
    *(Setting(f"exact {s}+{s}", (s, s), {}) for s in (12, 24, 48)),
    Setting(
        "exact 48+48, grid + T + empty skips",
        (48, 48),
        {"occupancy_epsilon": EPS, "transmittance_threshold": SKIP, "empty_threshold": SKIP},
    ),
    Setting("exact 48+48, all skips (grid in both passes + T + empty)", (48, 48), ALL_SKIPS),
    *(
        Setting(
            f"baked k {k} {s}+{s}{skips}",
            (s, s),
            {"occupancy_epsilon": EPS, "baked_subdivisions": k} | BAKED_SKIPS[skips],
        )
        for k in (2, 4, 6)
        for s in (24, 48)
        for skips in ("", ", T + empty skips")
    ),
    # Two levels (docs/baked.md, "Two levels"): k_f in the bricks a surface crosses, k 4 elsewhere;
    # k_f 16 also with more samples (a lookup costs the same at any k_f, so more samples are cheap),
    # coarse ones first: at k_f 16 a coarse sample buys more of the error than a fine one
    # (bench/RESULTS.md, "More coarse samples than fine").
    # "all skips" adds the grid to the coarse pass: the field's lookups in empty cells are nearly
    # transparent anyway (2.3e-4 at most on a pixel; bench/RESULTS.md, "A faster lookup").
    *(
        Setting(
            f"baked k 4 / {kf} {c}+{f}{skips}",
            (c, f),
            {"occupancy_epsilon": EPS, "baked_subdivisions": 4, "baked_fine_subdivisions": kf}
            | BAKED_SKIPS[skips],
        )
        for kf, (c, f), variants in (
            (10, (24, 24), ("", ", T + empty skips")),
            (10, (48, 48), ("", ", T + empty skips", ", all skips")),
            (16, (48, 48), ("", ", T + empty skips", ", all skips")),
            (16, (56, 48), (", all skips",)),
            (16, (64, 48), (", all skips",)),
            (16, (56, 56), (", all skips",)),
            (16, (64, 64), ("", ", T + empty skips", ", all skips")),
            (16, (80, 80), (", all skips",)),
            (16, (96, 64), (", all skips",)),
            (16, (96, 96), (", all skips",)),
        )
        for skips in variants
    ),
]


def eg3d_timer(src: str, head: TriplaneData, cams: np.ndarray, repeats: int):
    """ms per frame of EG3D's ImportanceRenderer at 48+48 on ``cams`` (bench/eg3d_speed.py's set-up)."""
    import torch

    renderer, rays, decoder = eg3d_renderer(Path(src), head.w0, head.b0, head.w1, head.b1)
    options = {
        "ray_start": head.ray_start,
        "ray_end": head.ray_end,
        "box_warp": head.box_warp,
        "depth_resolution": 48,
        "depth_resolution_importance": 48,
        "disparity_space_sampling": False,
        "clamp_mode": "softplus",
        "white_back": False,
    }
    planes = torch.from_numpy(head.planes).unsqueeze(0)

    def frame() -> None:
        with torch.no_grad():
            for c in cams:
                cam = torch.from_numpy(np.asarray(c, np.float32)).unsqueeze(0)
                origins, directions = rays(cam[:, :16].view(-1, 4, 4), cam[:, 16:25].view(-1, 3, 3), R)
                renderer(planes, decoder, origins, directions, options)

    frame()
    return timed(frame, repeats)[0] / len(cams)


def field_of(st: Setting) -> tuple[int, int] | None:
    """The field a setting renders with, (k, k_f) (k_f 0: one level), or None (exact mode)."""
    k = st.kwargs.get("baked_subdivisions")
    return None if k is None else (k, st.kwargs.get("baked_fine_subdivisions", 0))


def measure(
    name: str, head: TriplaneData, repeats: int, eg3d_src: str | None, settings: list[Setting]
) -> dict:
    tri = head.to_native()
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=PITCH) for y in YAWS])
    common = {"resolution": R, "outputs": ["rgb"]}
    fine = {"depth_resolution": 192, "depth_resolution_importance": 192}
    ref = lp3d_render.render(tri, cams, **common, **fine)["rgb"]
    bakes = {}
    for k in sorted({field_of(st) for st in settings if field_of(st)}):
        start = time.perf_counter()
        field = bake(tri, k)
        bakes[k] = {
            "s": time.perf_counter() - start,
            "bricks": field.bricks,
            "cells": field.cells,
            "mib": field.device_bytes / 2**20,
        }
    rows = []
    held = max(bakes) if bakes else None  # the triplane holds one field, the last baked
    for st in settings:
        k = field_of(st)
        if k is not None and k != held:  # the field for this k
            bake(tri, k)
            held = k

        def call(st: Setting = st) -> np.ndarray:
            coarse, fine = st.samples
            samples = {"depth_resolution": coarse, "depth_resolution_importance": fine}
            return lp3d_render.render(tri, cams, **common, **samples, **st.kwargs)["rgb"]

        rgb = call()
        ms = timed(call, repeats)[0] / len(cams)
        rows.append(
            {
                "setting": st.name,
                "baked": k,  # (k, k_f) or None
                "ms": ms,
                "psnr": statistics.mean(psnr_db(rgb[i], ref[i]) for i in range(len(cams))),
                "max_err": float(np.abs(rgb - ref).max()),
            }
        )
        print(f"  {name}: {st.name}: {ms:.1f} ms, {rows[-1]['psnr']:.2f} dB", file=sys.stderr, flush=True)
    eg3d_ms = eg3d_timer(eg3d_src, head, cams, repeats) if eg3d_src else None
    return {"scene": name, "rows": rows, "bakes": bakes, "eg3d_ms": eg3d_ms}


def report(results: list[dict], args: argparse.Namespace) -> str:
    info = lp3d_render.adapter_info()
    lines = [
        f"Command: `EG3D_SRC=... python bench/baked.py --repeats {args.repeats}"
        + (f" --only '{args.only}'" if args.only else "")
        + "`  ",
        f"{platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, "
        f"{time.strftime('%Y-%m-%d')}; adapter {info.get('name')} ({info.get('driver_info', '')})",
        "",
    ]
    for res in results:
        rows, eg3d = res["rows"], res["eg3d_ms"]
        exact48 = next(r for r in rows if r["setting"] == "exact 48+48")
        exact24 = next(r for r in rows if r["setting"] == "exact 24+24")
        lines += [
            f"**{res['scene']}** (EG3D ImportanceRenderer 48+48: "
            + (f"{eg3d:.0f} ms/frame)" if eg3d else "not run: EG3D_SRC unset)"),
            "",
            "| setting | ms/frame | PSNR vs exact 192+192 | max abs err | EG3D 48+48 / this |",
            "|---|---|---|---|---|",
        ]
        for r in rows:
            speed = f"{eg3d / r['ms']:.1f}×" if eg3d else "–"
            cells = f"{r['ms']:.1f} | {r['psnr']:.2f} | {r['max_err']:.3f}"
            lines.append(f"| {r['setting']} | {cells} | {speed} |")
        lines += [
            "",
            "| k | cells | bricks | MiB | bake s | frames to amortise vs exact 48+48 |",
            "|---|---|---|---|---|---|",
        ]
        for k, b in res["bakes"].items():
            own = [r for r in rows if r["baked"] == k]
            if not own:
                continue
            saved = exact48["ms"] - min(own, key=lambda r: r["ms"])["ms"]
            frames = math.ceil(b["s"] * 1e3 / saved) if saved > 0 else "never"
            size = f"{b['cells']}³ | {b['bricks']} | {b['mib']:.1f}"
            label = f"{k[0]} / {k[1]}" if k[1] else f"{k[0]}"
            lines.append(f"| {label} | {size} | {b['s']:.2f} | {frames} |")
        lines.append("")
        for bar, ref in (("exact 48+48", exact48), ("exact 24+24", exact24)):
            mine = [r for r in rows if r["baked"]]
            if not mine:
                continue
            ok = [r for r in mine if r["psnr"] >= ref["psnr"]]
            if ok:
                best = min(ok, key=lambda r: r["ms"])
                vs = f", {eg3d / best['ms']:.1f}× EG3D" if eg3d else ""
                lines.append(
                    f"- fastest baked setting at {bar}'s error ({ref['psnr']:.2f} dB) or better: "
                    f"{best['setting']}, {best['ms']:.1f} ms ({ref['ms'] / best['ms']:.1f}× {bar}{vs})"
                )
            else:
                top = max(mine, key=lambda r: r["psnr"])
                lines.append(
                    f"- no baked setting reaches {bar}'s error ({ref['psnr']:.2f} dB); the best is "
                    f"{top['setting']} at {top['psnr']:.2f} dB"
                )
        lines.append("")
    return "\n".join(lines)


def plot(results: list[dict], path: Path) -> None:
    """Time (log) against PSNR per scene: exact settings as circles, baked as squares."""
    from PIL import Image, ImageDraw

    w, h, m = 960, 600, 70
    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    allrows = [r for res in results for r in res["rows"]]
    t0, t1 = math.log10(min(r["ms"] for r in allrows) * 0.8), math.log10(max(r["ms"] for r in allrows) * 1.25)
    p0, p1 = min(r["psnr"] for r in allrows) - 2, max(r["psnr"] for r in allrows) + 2

    def xy(r: dict) -> tuple[float, float]:
        x = m + (math.log10(r["ms"]) - t0) / (t1 - t0) * (w - 2 * m)
        y = h - m - (r["psnr"] - p0) / (p1 - p0) * (h - 2 * m)
        return x, y

    d.rectangle([m, m, w - m, h - m], outline="black")
    for ms in (10, 30, 100, 300, 1000, 3000):
        if t0 <= math.log10(ms) <= t1:
            x = m + (math.log10(ms) - t0) / (t1 - t0) * (w - 2 * m)
            d.line([x, h - m, x, h - m + 6], fill="black")
            d.text((x - 12, h - m + 10), f"{ms} ms", fill="black")
    for db in range(int(p0) // 5 * 5 + 5, int(p1) + 1, 5):
        y = h - m - (db - p0) / (p1 - p0) * (h - 2 * m)
        d.line([m - 6, y, m, y], fill="black")
        d.text((m - 40, y - 6), f"{db} dB", fill="black")
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e"]
    # The legend goes in the inner corner with the fewest points under it.
    lw, lh = 270, 16 * (len(results) + 1) + 8
    corners = [(x, y) for x in (m + 10, w - m - lw) for y in (m + 10, h - m - lh)]

    def covered(corner: tuple[float, float]) -> int:
        x0, y0 = corner
        return sum(x0 - 8 <= x <= x0 + lw and y0 - 8 <= y <= y0 + lh for x, y in map(xy, allrows))

    lx, ly = min(corners, key=covered)
    for i, res in enumerate(results):
        c = colours[i % len(colours)]
        # The bar a baked setting must reach: this scene's exact 48+48, dotted across the plot.
        bar = next((r for r in res["rows"] if r["setting"] == "exact 48+48"), None)
        if bar:
            y = xy(bar)[1]
            for x in range(m, w - m, 8):
                d.line([x, y, x + 3, y], fill=c)
        for r in res["rows"]:
            x, y = xy(r)
            box = [x - 4, y - 4, x + 4, y + 4]
            (d.rectangle if r["baked"] else d.ellipse)(box, fill=c if r["baked"] else None, outline=c)
        d.text((lx, ly + 16 * i), res["scene"], fill=c)
    title = "baked field (squares), exact mode (circles; dotted: exact 48+48): ms per 128x128 frame vs PSNR"
    d.text((m, 20), title, fill="black")
    d.text((lx, ly + 16 * len(results)), "PSNR against exact 192+192", fill="black")
    img.save(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3, help="timed calls per setting (default 3)")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    p.add_argument("--plot", type=Path, help="write the time-vs-error plot (PNG) here")
    p.add_argument(
        "--only",
        help="run only the settings whose name matches this regular expression (exact 24+24 and "
        "48+48, which the report compares against, always run)",
    )
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats must be >= 1")
    src = os.environ.get("EG3D_SRC")
    always = ("exact 24+24", "exact 48+48")
    settings = [st for st in SETTINGS if not args.only or st.name in always or re.search(args.only, st.name)]
    results = []
    for name, head in scenes():
        print(f"{name} ...", file=sys.stderr, flush=True)
        results.append(measure(name, head, args.repeats, src, settings))
    text = report(results, args)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    if args.plot:
        plot(results, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
