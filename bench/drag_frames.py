"""How long the viewer's baked drag frames take to render, alone (no window), for A/B of builds.

    python bench/drag_frames.py [--builds now= before=/tmp/old-build] [--rounds 2] [--out F]

``lp3d-view`` draws a moving view from its fine field (k 4 / 16) at 128² · 64+48 (the rung of the
still frame's 48+48, with a third more coarse samples), or at 48+24 when that misses the frame
budget (``crates/viewer/src/bake.rs``, ``quality.rs``). This times those two frames with the
viewer's skips on the scenes a user opens (the shipped encoder's triplanes of frontal renders of
teacher heads 0 and 1000003, 64² planes; three views, yaw -30/0/30, pitch 5, one call), as the
median of ``--repeats`` calls per view, after one untimed call that compiles the kernel. Each field
is baked once and saved under ``--fields`` (reused by later runs; a saved field is checked against
its triplane when loaded, and baked again if it does not fit; delete the folder to encode the scenes
again with another model).

Builds: ``NAME=PATH`` runs this script's timing in a child process with ``PATH`` first on
``PYTHONPATH`` (an ``lp3d_render`` built elsewhere, e.g. ``pip install --target PATH .`` of an older
commit; an empty PATH is the installed one), the builds alternated ``--rounds`` times so that a
machine's slow spell hits both. Every frame's SHA-256 is compared across builds ("same bits").
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

from harness import FINE_FIELD as FINE  # bench/ is on sys.path when run as a script
from harness import VIEWER_SKIPS, child_rows, emit_table

os.environ.setdefault("LP3D_KERNEL", "fast")

SEEDS = (0, 1_000_003)
YAWS = (-30.0, 0.0, 30.0)
PITCH = 5.0
#: The viewer's fine field (k, k_f) and its frames' skips, as bench/drag_error.py states them.
FIELD = {
    "subdivisions": FINE[0],
    "fine_subdivisions": FINE[1],
    "occupancy_epsilon": VIEWER_SKIPS["occupancy_epsilon"],
    "depth_resolution": 24,
}
SKIPS = VIEWER_SKIPS | {"baked_subdivisions": FINE[0], "baked_fine_subdivisions": FINE[1]}
#: (coarse, fine): the drag rung and the first baked-only rung, as the fine field draws them.
FRAMES = ((64, 48), (48, 24))


def prepare(fields: Path) -> list[object]:
    """The scenes' triplanes on the GPU with their fine fields attached (baked and saved once)."""
    import lp3d_render
    from harness import saved_encoder_output  # bench/ is on sys.path when run as a script
    from lp3d.render.baked import load_baked, save_baked

    tris = []
    for seed in SEEDS:
        tri = saved_encoder_output(seed, fields).to_native()
        field_path = fields / f"encoder-{seed}.field-k4-16.npz"
        try:
            load_baked(field_path, tri)
        except (OSError, ValueError) as e:
            if field_path.exists():  # saved by another version, or damaged: bake it again
                print(f"not reusing {field_path}: {e}", file=sys.stderr, flush=True)
            print(f"baking head {seed}'s fine field (about a minute)", file=sys.stderr, flush=True)
            save_baked(field_path, lp3d_render.bake(tri, **FIELD), tri)
        tris.append(tri)
    return tris


def child(fields: Path, repeats: int) -> None:
    """Times every frame once per repeat in this process; prints one JSON line per frame."""
    import lp3d_render
    from lp3d.render.camera import look_at_camera

    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=PITCH) for y in YAWS])
    for seed, tri in zip(SEEDS, prepare(fields), strict=True):
        for coarse, fine in FRAMES:

            def frame(tri: object = tri, coarse: int = coarse, fine: int = fine) -> np.ndarray:
                return lp3d_render.render(
                    tri,
                    cams,
                    resolution=128,
                    depth_resolution=coarse,
                    depth_resolution_importance=fine,
                    outputs=["rgb"],
                    **SKIPS,
                )["rgb"]

            frame()  # compiles the kernel, or loads it from Mesa's cache
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                rgb = frame()
                times.append((time.perf_counter() - start) / len(YAWS))
            digest = hashlib.sha256(np.ascontiguousarray(rgb).tobytes()).hexdigest()
            row = {"seed": seed, "frame": f"{coarse}+{fine}", "ms": 1e3 * statistics.median(times)}
            print(json.dumps(row | {"sha256": digest}), flush=True)


def run_build(path: str, args: argparse.Namespace) -> list[dict]:
    env = dict(os.environ)
    if path:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (path, env.get("PYTHONPATH", "")) if p)
    return child_rows(__file__, ["--fields", str(args.fields), "--repeats", str(args.repeats)], env)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--builds", nargs="+", default=["now="], help="NAME=PATH (PATH first on PYTHONPATH)")
    p.add_argument("--rounds", type=int, default=2, help="alternations of the builds")
    p.add_argument("--repeats", type=int, default=5, help="timed calls per frame and process")
    p.add_argument("--fields", type=Path, default=Path("/tmp/lp3d-drag-fields"), help="saved scenes")
    p.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        child(args.fields, args.repeats)
        return 0
    builds = []
    for spec in args.builds:
        name, sep, path = spec.partition("=")
        if not sep or not name:
            p.error(f"--builds: expected NAME=PATH, got {spec!r}")
        if path and not Path(path).is_dir():
            p.error(f"--builds: {path} is not a folder")
        builds.append((name, path))
    ms: dict[tuple[str, int, str], list[float]] = {}
    digests: dict[tuple[int, str], set[str]] = {}
    for r in range(args.rounds):
        for name, path in builds:
            for row in run_build(path, args):
                ms.setdefault((name, row["seed"], row["frame"]), []).append(row["ms"])
                digests.setdefault((row["seed"], row["frame"]), set()).add(row["sha256"])
                at = f"head {row['seed']} {row['frame']}"
                print(f"round {r + 1} {name}: {at} {row['ms']:.1f} ms", flush=True)
    lines = [
        f"Command: `python bench/drag_frames.py {' '.join(sys.argv[1:])}`  ",
        f"{platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}; "
        f"LP3D_KERNEL={os.environ['LP3D_KERNEL']}; ms per 128² view, each round's median of "
        f"{args.repeats} calls",
        "",
        "| head | frame | " + " | ".join(f"{name}: ms per round" for name, _ in builds) + " | same bits |",
        "|---|---|" + "---|" * len(builds) + "---|",
    ]
    for seed in SEEDS:
        for coarse, fine in FRAMES:
            frame = f"{coarse}+{fine}"
            cells = [", ".join(f"{v:.1f}" for v in ms[(name, seed, frame)]) for name, _ in builds]
            same = "yes" if len(digests[(seed, frame)]) == 1 else "no"
            lines.append(f"| {seed} | 128² · {frame} | " + " | ".join(cells) + f" | {same} |")
    emit_table(lines, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
