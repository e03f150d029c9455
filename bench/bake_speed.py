"""How long the viewer's two baked fields take to bake, with each kernel's decoder: the quick field
(k 4 / 10) and the fine one (k 4 / 16) that ``lp3d-view`` bakes after opening a file, for the
scenes a user opens (the shipped encoder's triplane of a frontal render of a teacher head, 64²
planes) and the teacher head itself (256² planes).

    python bench/bake_speed.py --out /tmp/bake_speed.md

The bake kernel uses the decoder of the kernel that exact renders use (``LP3D_KERNEL``): the fast
kernel's unrolled one, or the quick kernel's rolled one (what every bake used before 2026-11-29).
Each bake runs in a fresh process per kernel, alternated, after an untimed bake of a tiny field that
compiles the kernel (or loads it from Mesa's shader cache). Reported: the GPU part of each bake
(``BakedField.bake_seconds``), the field's size, and whether the two kernels' fields are identical
bit for bit (a SHA-256 of every stored value).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: The viewer's fields (crates/viewer/src/bake.rs: QUICK_FIELD, FINE_FIELD), baked for 24 coarse samples.
FIELDS = {"quick k 4 / 10": (4, 10), "fine k 4 / 16": (4, 16)}
KERNELS = ("fast", "quick")

CHILD = r"""
import hashlib, json, sys
import numpy as np
import lp3d_render
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import load_triplane
tiny = coloured_sphere(size=16).to_native()
lp3d_render.bake(tiny, subdivisions=2, occupancy_epsilon=1e-4)  # compiles (untimed)
tri = load_triplane(sys.argv[1]).to_native()
out = {}
for name, (k, kf) in json.loads(sys.argv[2]).items():
    f = lp3d_render.bake(
        tri, subdivisions=k, fine_subdivisions=kf, occupancy_epsilon=1e-4, depth_resolution=24
    )
    h = hashlib.sha256()
    for a in (f.index, f.values, f.fine_values):
        h.update(np.ascontiguousarray(a).tobytes())
    out[name] = {"s": f.bake_seconds, "mib": f.device_bytes / 2**20, "bricks": f.bricks,
                 "fine_bricks": f.fine_bricks, "sha256": h.hexdigest()}
print(json.dumps(out))
"""


def bake_once(scene: Path, kernel: str) -> dict:
    env = {**os.environ, "LP3D_KERNEL": kernel}
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(scene), json.dumps(FIELDS)],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the bake with LP3D_KERNEL={kernel} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="markdown table to write")
    p.add_argument("--rounds", type=int, default=2, help="alternations of the two kernels (default 2)")
    p.add_argument("--scenes", default="encoder,teacher", help="comma list of encoder, teacher")
    args = p.parse_args(argv)
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not scenes or any(s not in ("encoder", "teacher") for s in scenes) or args.rounds < 1:
        p.error("--scenes: a comma list of encoder, teacher; --rounds at least 1")

    import lp3d_render
    from harness import encoder_output  # bench/ is on sys.path when run as a script
    from lp3d.render.triplane_io import save_triplane
    from lp3d.teachers.procedural import ProceduralTeacher

    rows = []
    with tempfile.TemporaryDirectory(prefix="lp3d-bake-speed-") as tmp:
        head = ProceduralTeacher().sample(0)
        for scene in scenes:
            path = Path(tmp) / f"{scene}.npz"
            save_triplane(path, head if scene == "teacher" else encoder_output(head))
            runs: dict[str, list[dict]] = {k: [] for k in KERNELS}
            for _ in range(args.rounds):
                for kernel in KERNELS:
                    r = bake_once(path, kernel)
                    runs[kernel].append(r)
                    print(
                        scene,
                        kernel,
                        {n: round(v["s"], 1) for n, v in r.items()},
                        file=sys.stderr,
                        flush=True,
                    )
            for name in FIELDS:
                fast = [r[name]["s"] for r in runs["fast"]]
                quick = [r[name]["s"] for r in runs["quick"]]
                digests = {r[name]["sha256"] for k in KERNELS for r in runs[k]}
                first = runs["fast"][0][name]
                rows.append(
                    f"| {scene} | {name} | {first['bricks']} ({first['fine_bricks']} fine), "
                    f"{first['mib']:.0f} MiB "
                    f"| {', '.join(f'{s:.1f}' for s in quick)} | {', '.join(f'{s:.1f}' for s in fast)} "
                    f"| {statistics.median(quick) / statistics.median(fast):.2f}× "
                    f"| {'yes' if len(digests) == 1 else 'NO'} |"
                )
    info = lp3d_render.adapter_info()
    text = "\n".join(
        [
            f"Command: `python bench/bake_speed.py --rounds {args.rounds} --scenes {args.scenes} "
            f"--out {args.out}`  ",
            f"{platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}, load "
            f"{os.getloadavg()[0]:.1f} at the end; {info.get('name')} ({info.get('driver_info', '')})",
            "",
            "| scene | field | bricks, size | bake s, quick kernel's decoder | bake s, fast kernel's decoder "
            "| quick / fast (medians) | same field |",
            "|---|---|---|---|---|---|---|",
            *rows,
            "",
        ]
    )
    print(text)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
