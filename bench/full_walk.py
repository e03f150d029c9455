"""What exact early termination saves: exact mode with every sample walked against walks that end
once nothing left can change an output (docs/numerics.md, "Exact early termination").

    python bench/full_walk.py [--rounds 2] [--repeats 3] [--out F]

Each scene is rendered in exact mode (128² · 48+48, yaw 20, pitch 5, as ``bench/eg3d_speed.py``) with
every output and with RGB and depth alone, in child processes with ``LP3D_FULL_WALK=1`` (every
sample) and ``0`` (the default) in turn, ``--rounds`` times, so that a slow spell of the machine hits
both. Reported: each round's median of ``--repeats`` calls, and whether the two give the same bits
(SHA-256 of every output). The scenes: ``bench/render_bench.py``'s random triplane (a haze whose
transmittance never gets small), two procedural teacher heads (256² planes) and the shipped
encoder's triplanes of the same heads (64² planes; encoded once and kept under ``--scenes``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from harness import child_rows, emit_table  # bench/ is on sys.path when run as a script

os.environ.setdefault("LP3D_KERNEL", "fast")

SEEDS = (0, 1_000_003)
OUTPUTS = {"all": None, "rgb": ["rgb", "depth"]}
WALKS = (("every sample", "1"), ("ended walks", "0"))


def scenes(folder: Path) -> list[tuple[str, object]]:
    """(name, native triplane) of every scene, the encoder's outputs encoded once and saved."""
    from harness import (
        random_triplane,  # bench/ is on sys.path when run as a script
        saved_encoder_output,  # bench/ is on sys.path when run as a script
    )
    from lp3d.teachers import ProceduralTeacher

    out: list[tuple[str, object]] = [("random triplane", random_triplane().to_native())]
    for seed in SEEDS:
        out.append((f"teacher head {seed}", ProceduralTeacher().sample(seed).to_native()))
    for seed in SEEDS:
        out.append((f"encoder output, head {seed}", saved_encoder_output(seed, folder).to_native()))
    return out


def child(folder: Path, repeats: int) -> None:
    """Times every scene and output in this process; prints one JSON line each."""
    import lp3d_render
    from lp3d.render.camera import look_at_camera

    camera = look_at_camera(yaw_deg=20.0, pitch_deg=5.0)
    for name, tri in scenes(folder):
        for label, outputs in OUTPUTS.items():

            def frame(tri: object = tri, outputs: list[str] | None = outputs) -> dict[str, np.ndarray]:
                return lp3d_render.render(
                    tri,
                    camera,
                    resolution=128,
                    depth_resolution=48,
                    depth_resolution_importance=48,
                    outputs=outputs,
                )

            frame()  # compiles the kernel, or loads it from Mesa's cache
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                out = frame()
                times.append(time.perf_counter() - start)
            digest = hashlib.sha256()
            for key in sorted(out):
                digest.update(np.ascontiguousarray(out[key]).tobytes())
            row = {"scene": name, "outputs": label, "ms": 1e3 * statistics.median(times)}
            print(json.dumps(row | {"sha256": digest.hexdigest()}), flush=True)


def run_walk(full: str, args: argparse.Namespace) -> list[dict]:
    env = dict(os.environ, LP3D_FULL_WALK=full)
    return child_rows(__file__, ["--scenes", str(args.scenes), "--repeats", str(args.repeats)], env)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=2, help="alternations of the two (default 2)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per scene and process (default 3)")
    p.add_argument("--scenes", type=Path, default=Path("/tmp/lp3d-drag-fields"), help="saved encoder outputs")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.rounds < 1 or args.repeats < 1:
        p.error("--rounds and --repeats must be >= 1")
    if args.child:
        child(args.scenes, args.repeats)
        return 0
    ms: dict[tuple[str, str, str], list[float]] = {}
    digests: dict[tuple[str, str], set[str]] = {}
    order: list[tuple[str, str]] = []
    for r in range(args.rounds):
        for walk, full in WALKS:
            for row in run_walk(full, args):
                key = (row["scene"], row["outputs"])
                if key not in order:
                    order.append(key)
                ms.setdefault((walk, *key), []).append(row["ms"])
                digests.setdefault(key, set()).add(row["sha256"])
                print(f"round {r + 1} {walk}: {key[0]} ({key[1]}) {row['ms']:.0f} ms", flush=True)
    lines = [
        f"Command: `python bench/full_walk.py {' '.join(sys.argv[1:])}`  ",
        f"{platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}; "
        f"LP3D_KERNEL={os.environ['LP3D_KERNEL']}; exact mode, 128² · 48+48, ms per frame, each round's "
        f"median of {args.repeats} calls",
        "",
        "| scene | outputs | every sample: ms per round | ended walks: ms per round | saved (medians) "
        "| same bits |",
        "|---|---|---|---|---|---|",
    ]
    for scene, label in order:
        full = ms[("every sample", scene, label)]
        ended = ms[("ended walks", scene, label)]
        saved = 1.0 - statistics.median(ended) / statistics.median(full)
        same = "yes" if len(digests[(scene, label)]) == 1 else "**no**"
        cells = [", ".join(f"{v:.0f}" for v in x) for x in (full, ended)]
        lines.append(f"| {scene} | {label} | {cells[0]} | {cells[1]} | {100 * saved:.0f}% | {same} |")
    emit_table(lines, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
