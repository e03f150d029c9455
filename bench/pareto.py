"""Run time against error: lp3d_render's settings and skips on several scenes, against a
high-quality exact render, with the torch twin timed in the same run.

    python bench/pareto.py [--resolution 64] [--out bench] [--quick] [--triplane head.npz --no-builtin]

Scenes: procedural teacher identities (portraits: opaque heads on a backdrop) and random fog
(white-noise planes under a large density gain: the worst case, nothing to skip). The reference
for each scene is exact mode (EG3D semantics) with 192+192 samples. Every setting is timed
(median of --repeats after a warm-up) and scored by PSNR (RGB mapped to [0, 1]) and max abs error
against that reference. Writes a Markdown table to stdout and a Pareto plot PNG to --out.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

import lp3d_render
from harness import timed  # bench/ is on sys.path when run as a script
from lp3d.render.camera import look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.settings import Skips
from lp3d.render.triplane import TriplaneData
from lp3d.render.triplane_io import load_triplane
from lp3d.teachers import ProceduralTeacher

# Time the steady state: the fast kernel, not the quick one the renderer draws with while the fast
# one compiles in the background on a machine whose shader cache lacks it (README, "first render").
os.environ.setdefault("LP3D_KERNEL", "fast")


@dataclass(frozen=True)
class Setting:
    name: str
    samples: tuple[int, int]
    #: The renderer's skips (lp3d.render.settings.Skips); with occupancy_epsilon the grid is baked at
    #: G = 64 before timing.
    skips: Skips = Skips()


SETTINGS = (
    [Setting(f"exact {s}+{n}", (s, n)) for s, n in [(12, 12), (24, 24), (48, 48), (96, 96)]]
    + [
        Setting(f"T<{t:g} empty<{e:g} {s}+{n}", (s, n), Skips(t, e))
        for s, n in [(24, 24), (48, 48)]
        for t, e in [(1e-4, 1e-4), (1e-3, 1e-3), (1e-2, 1e-2)]
    ]
    + [
        Setting(f"grid eps {g:g} {s}+{n}", (s, n), Skips(occupancy_epsilon=g))
        for s, n in [(24, 24), (48, 48)]
        for g in (1e-4, 1e-3)
    ]
    + [
        Setting(f"grid eps 1e-4 T<1e-3 empty<1e-3 {s}+{n}", (s, n), Skips(1e-3, 1e-3, 1e-4))
        for s, n in [(24, 24), (48, 48)]
    ]
    + [
        Setting(f"grid eps 1e-4 + coarse, T<1e-3 empty<1e-3 {s}+{n}", (s, n), Skips(1e-3, 1e-3, 1e-4, True))
        for s, n in [(24, 24), (48, 48)]
    ]
)
#: The --quick subset: exact 12/24/48, the skips at 24+24, the grid (composite, combined with the
#: other skips, and in the coarse pass too) at 24+24 and 48+48.
QUICK = [0, 1, 2, 4, 5, 6, 10, 12, 14, 15, 16, 17]


def fog(seed: int = 0, size: int = 64) -> TriplaneData:
    rng = np.random.default_rng(seed)
    w1 = (rng.standard_normal((33, 64)) / 8).astype(np.float32)
    w1[0] *= 6.0
    return TriplaneData(
        planes=rng.standard_normal((3, 32, size, size)).astype(np.float32),
        w0=(rng.standard_normal((64, 32)) / np.sqrt(32)).astype(np.float32),
        b0=np.zeros(64, np.float32),
        w1=w1,
        b1=np.zeros(33, np.float32),
        source="random fog",
    )


def plot(rows: list[dict], path: Path) -> None:
    """A log-time vs PSNR scatter, one colour per scene, exact settings as circles, skips as squares."""
    from PIL import Image, ImageDraw

    w, h, m = 900, 560, 70
    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    finite = [r for r in rows if math.isfinite(r["psnr"])]
    tmin = min(r["ms"] for r in rows) * 0.8
    tmax = max(r["ms"] for r in rows) * 1.25
    pmin = min(20.0, min(r["psnr"] for r in finite))
    pmax = max(r["psnr"] for r in finite) + 5
    lt0, lt1 = math.log10(tmin), math.log10(tmax)

    def x(ms: float) -> float:
        return m + (math.log10(ms) - lt0) / (lt1 - lt0) * (w - 2 * m)

    def y(p: float) -> float:
        return h - m - (min(p, pmax) - pmin) / (pmax - pmin) * (h - 2 * m)

    d.rectangle([m, m, w - m, h - m], outline="black")
    for p in range(int(pmin // 10 * 10), int(pmax) + 1, 10):
        if pmin <= p <= pmax:
            d.line([m, y(p), w - m, y(p)], fill=(225, 225, 225))
            d.text((m - 40, y(p) - 6), f"{p} dB", fill="black")
    for e in range(math.floor(math.log10(tmin)), math.ceil(math.log10(tmax)) + 1):
        for k in (1, 2, 5):
            ms = k * 10**e
            if tmin <= ms <= tmax:
                d.line([x(ms), m, x(ms), h - m], fill=(235, 235, 235))
                d.text((x(ms) - 12, h - m + 6), f"{ms:g}", fill="black")
    d.text((w // 2 - 80, h - 30), "ms per frame (log scale)", fill="black")
    d.text((10, 10), "PSNR vs exact 192+192 (higher is better); circles: exact, squares: skips", fill="black")
    colours = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189)]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    for i, scene in enumerate(scenes):
        c = colours[i % len(colours)]
        d.ellipse([w - m - 160, m + 10 + 14 * i, w - m - 152, m + 18 + 14 * i], outline=c, width=2)
        d.text((w - m - 146, m + 8 + 14 * i), scene, fill=c)
        for r in rows:
            if r["scene"] != scene:
                continue
            px, py = x(r["ms"]), y(r["psnr"] if math.isfinite(r["psnr"]) else pmax)
            box = [px - 5, py - 5, px + 5, py + 5]
            (d.ellipse if r["exact"] else d.rectangle)(box, outline=c, width=2)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("bench"))
    parser.add_argument("--quick", action="store_true", help="one teacher identity, fewer settings")
    parser.add_argument(
        "--triplane",
        type=Path,
        action="append",
        default=[],
        help="also a triplane .npz, e.g. an encoder's output from lp3d encode (repeatable)",
    )
    parser.add_argument("--no-builtin", action="store_true", help="only the --triplane scenes")
    args = parser.parse_args(argv)

    teacher = ProceduralTeacher()
    scenes = {"teacher seed 0": teacher.sample(0), "teacher seed 3": teacher.sample(3), "random fog": fog()}
    if args.quick:
        scenes = {"teacher seed 0": scenes["teacher seed 0"], "random fog": scenes["random fog"]}
    if args.no_builtin:
        scenes = {}
    for path in args.triplane:
        scenes[path.stem] = load_triplane(path)
    if not scenes:
        parser.error("no scenes: give --triplane or drop --no-builtin")
    settings = [SETTINGS[i] for i in QUICK] if args.quick else SETTINGS
    cam = look_at_camera(yaw_deg=20.0, pitch_deg=5.0)
    r = args.resolution
    info = lp3d_render.adapter_info()

    try:
        from lp3d.render.torch_twin import render_with_twin
    except ImportError:
        render_with_twin = None

    rows = []
    torch_ms = {}
    for scene_name, data in scenes.items():
        tri = data.to_native()
        # Warm-up / compile, and bake the occupancy grid (G = 64) outside the timings.
        lp3d_render.render(tri, cam, resolution=8, occupancy_epsilon=1e-4)
        ref = lp3d_render.render(
            tri, cam, resolution=r, depth_resolution=192, depth_resolution_importance=192, outputs=["rgb"]
        )["rgb"]
        if render_with_twin is not None:
            torch_ms[scene_name], _ = timed(
                lambda data=data: render_with_twin(
                    data, cam, resolution=r, depth_resolution=48, depth_resolution_importance=48
                ),
                args.repeats,
            )
        for st in settings:
            s, n = st.samples
            ms, out = timed(
                lambda tri=tri, s=s, n=n, st=st: lp3d_render.render(
                    tri,
                    cam,
                    resolution=r,
                    depth_resolution=s,
                    depth_resolution_importance=n,
                    outputs=["rgb"],
                    **asdict(st.skips),
                ),
                args.repeats,
            )
            rgb = out["rgb"]
            rows.append(
                {
                    "scene": scene_name,
                    "setting": st.name,
                    "ms": ms,
                    "psnr": psnr_db(rgb, ref),
                    "max": float(np.abs(rgb - ref).max() / 2),
                    "exact": st.skips.exact,
                }
            )
            print(f"{scene_name:16s} {st.name:28s} {ms:9.1f} ms  {rows[-1]['psnr']:6.1f} dB", file=sys.stderr)

    plot(rows, args.out / "pareto.png")
    print(
        f"Adapter: {info['name']} ({info['backend']}, {info['driver_info']}); R = {r}, RGB only, "
        f"camera yaw 20° pitch 5°.\n"
    )
    print("| scene | setting | ms/frame | PSNR vs exact 192+192 | max abs error | torch twin 48+48 / this |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        tw = torch_ms.get(row["scene"])
        ratio = "—" if tw is None else f"{tw / row['ms']:.2f}×"
        print(
            f"| {row['scene']} | {row['setting']} | {row['ms']:,.1f} | {row['psnr']:.1f} dB | "
            f"{row['max']:.1e} | {ratio} |"
        )
    for scene, tw in torch_ms.items():
        print(f"\ntorch twin ({scene}, exact 48+48, all outputs): {tw:,.1f} ms/frame", end="")
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
