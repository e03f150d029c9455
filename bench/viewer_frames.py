"""Viewer frame times while dragging: ``lp3d-view`` in a real window under Xvfb, at its default
final quality (128², 48+48) and frame budget (100 ms), drives a scripted drag (``--drag-frames``,
synthetic pointer events through egui, the same path as a mouse), then refines to the final image.
Each budget runs in up to three modes: ``baked`` (the default viewer: the drag starts once the
file's baked fields are ready, the quick one and then the fine one, and frames drawn while dragging
look samples up in the fine one at the final quality when that fits the budget), ``quick``
(``--no-fine-field``: the quick field only) and ``ladder`` (``--no-bake``: every frame decodes, the
drag drops down the quality ladder). The scene is a procedural teacher head (``--scene teacher``)
or the shipped encoder's triplane of a frontal render of it (``--scene encoder``, as ``lp3d demo``
lifts its teacher portrait: what a user opens).

    python bench/viewer_frames.py --out /tmp/viewer_frames.md
    python bench/viewer_frames.py --runs 3 --drag-frames 30 --budgets 100 --modes baked,ladder --out /tmp/v.md

Everything comes from the screenshot's JSON sidecar, which logs every rendered frame: its render time
(``render_ms``: from the start of the render call to the GPU finishing it), the time since the previous UI
frame began (``interval_ms``: what the user sees as the frame time, UI work included), its rung of the quality
ladder, whether it was drawn from the baked field and whether a pointer button was down. Reported per run: the
rungs drawn while dragging, median and 90th percentile of both times over the drag's frames, the median of the
window's own time per frame (a frame's interval less the render it holds: egui, painting and presenting), the
frames per second on screen while dragging (1000 / median interval), the time from releasing the pointer to
the final image on screen (``release → final``, the 200 ms settle included), the final frame's render time
and, in baked mode, the bake's time (the occupancy grid and the field, from the file opening to the field
being ready), and for a file of the shipped model (``--scene encoder``) the still image super-resolved (``lp3d
view`` picks the model's network: its 64² feature image rendered and run through it, after the exact image,
whose time is the final render's). A second table compares, for each rung, its first render in the process
with the median of its later ones: a rung that needed a pipeline compile would show a first render seconds
slower.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

XVFB = ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24"]


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), q))


MODES = ("baked", "quick", "ladder")
#: The viewer's flags for each mode.
MODE_FLAGS = {"baked": [], "quick": ["--no-fine-field"], "ladder": ["--no-bake"]}
SCENES = ("teacher", "encoder")


def _rung(f: dict) -> str:
    fine = f["depth_resolution_importance"]
    samples = f"{f['depth_resolution']}+{fine}" if fine else f"{f['depth_resolution']}"
    return f"{f['resolution']}² · {samples}" + (" baked" if f.get("baked") else "")


def run_once(scene: Path, work: Path, budget: float, mode: str, drag_frames: int, timeout: float) -> dict:
    shot = work / f"shot-{budget:g}-{mode}-{time.monotonic_ns()}.png"
    cmd = [
        *XVFB,
        sys.executable,
        "-m",
        "lp3d.cli",
        "view",
        *("--screenshot", str(shot), "--drag-frames", str(drag_frames)),
        *("--frame-budget-ms", str(budget), str(scene)),
        *MODE_FLAGS[mode],
    ]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    load = os.getloadavg()[0]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"lp3d-view failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    meta = json.loads(shot.with_suffix(".json").read_text())
    frames = meta["frames"]
    drag = [f for f in frames if f["dragging"]]
    if not drag:
        raise RuntimeError("no frame was rendered during the drag")
    rungs: dict[str, int] = {}
    for f in drag:
        rungs[_rung(f)] = rungs.get(_rung(f), 0) + 1
    render = [f["render_ms"] for f in drag]
    # The first drag frame's interval includes the wait before the drag started.
    interval = [f["interval_ms"] for f in drag[1:]] or [drag[0]["interval_ms"]]
    # A frame's interval (since the UI frame before began) holds the render of the UI frame before:
    # what is left of it when that render is taken off is the window's own work (egui, painting,
    # presenting), where the two UI frames are consecutive.
    window = [
        b["interval_ms"] - a["render_ms"]
        for a, b in zip(drag, drag[1:], strict=False)
        if b["ui_frame"] == a["ui_frame"] + 1
    ]
    bake = meta["bake"]
    if mode != "ladder" and bake["state"] != "ready":
        raise RuntimeError(f"the bake did not finish: {bake}")
    return {
        "budget": budget,
        "mode": mode,
        "bake_s": bake["job_seconds"],
        "field": bake["field"],
        "load": load,
        "quality": meta["quality"],
        "adapter": meta["adapter"],
        "rungs": rungs,
        "render_median": statistics.median(render),
        "render_p90": _percentile(render, 90),
        "interval_median": statistics.median(interval),
        "interval_p90": _percentile(interval, 90),
        "window_median": statistics.median(window) if window else float("nan"),
        "release_to_final": meta["drag"]["release_to_final_ms"],
        # The still image: the exact render at the final quality, then (a file of the shipped model)
        # its feature image super-resolved, which replaces it on screen.
        "final_ms": next(f["render_ms"] for f in reversed(frames) if not f.get("superres")),
        "superres_ms": next((f["render_ms"] for f in reversed(frames) if f.get("superres")), None),
        "frames": frames,
    }


SCENE_NAMES = {
    "teacher": "procedural teacher head",
    "encoder": "the shipped encoder's triplane of a frontal render of the procedural teacher head",
}


def first_vs_later(frames: list[dict]) -> list[tuple[str, float, float | None, int]]:
    """(rung, first render ms, median of later renders or None, number of later renders)."""
    by_rung: dict[str, list[float]] = {}
    for f in frames:
        by_rung.setdefault(_rung(f), []).append(f["render_ms"])
    return [
        (rung, times[0], statistics.median(times[1:]) if len(times) > 1 else None, len(times) - 1)
        for rung, times in by_rung.items()
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="markdown tables to write")
    p.add_argument("--runs", type=int, default=3, help="runs per budget (default 3)")
    p.add_argument("--drag-frames", type=int, default=30, help="UI frames the drag lasts (default 30)")
    p.add_argument("--budgets", default="100", help="comma list of frame budgets in ms (default 100)")
    p.add_argument("--modes", default="baked,ladder", help="comma list of baked, ladder (default both)")
    p.add_argument("--seed", type=int, default=0, help="procedural teacher head to show (default 0)")
    p.add_argument(
        "--scene",
        choices=SCENES,
        default="teacher",
        help="the teacher head itself, or the shipped encoder's triplane of a frontal render of it",
    )
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per run before giving up")
    args = p.parse_args(argv)
    try:
        budgets = [float(b) for b in args.budgets.split(",") if b.strip()]
    except ValueError:
        p.error(f"--budgets: a comma list of numbers, got {args.budgets!r}")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in MODES for m in modes):
        p.error(f"--modes: a comma list of {', '.join(MODES)}, got {args.modes!r}")
    if not budgets or args.runs < 1 or args.drag_frames < 1:
        p.error("--budgets, --runs and --drag-frames need at least one")
    if shutil.which("xvfb-run") is None:
        p.error("xvfb-run is missing: run scripts/install-system-deps.sh")

    from harness import encoder_output  # bench/ is on sys.path when run as a script
    from lp3d.render.triplane_io import save_triplane
    from lp3d.teachers.procedural import ProceduralTeacher

    results = []
    with tempfile.TemporaryDirectory(prefix="lp3d-viewer-frames-") as tmp:
        work = Path(tmp)
        scene = work / "head.npz"
        head = ProceduralTeacher().sample(args.seed)
        save_triplane(scene, head if args.scene == "teacher" else encoder_output(head))
        for mode in modes:  # warm the shader cache (untimed)
            run_once(scene, work, budgets[0], mode, 2, args.timeout)
        # Modes alternate run by run, so that a change in the machine's load hits both alike.
        for budget in budgets:
            for _ in range(args.runs):
                for mode in modes:
                    r = run_once(scene, work, budget, mode, args.drag_frames, args.timeout)
                    results.append(r)
                    print(
                        f"budget {budget:g} ms, {mode}: drag render {r['render_median']:.1f}/"
                        f"{r['render_p90']:.1f} ms, interval {r['interval_median']:.1f}/"
                        f"{r['interval_p90']:.1f} ms, window {r['window_median']:.1f} ms, "
                        f"release → final {r['release_to_final']:.0f} ms, "
                        f"bake {r['bake_s'] or 0:.1f} s, load {r['load']:.1f}",
                        flush=True,
                    )

    command = (
        f"python bench/viewer_frames.py --runs {args.runs} --drag-frames {args.drag_frames} "
        f"--budgets {args.budgets} --modes {args.modes} --scene {args.scene} --out {args.out}"
    )
    lines = [
        f"Command: `{command}`  ",
        f"{platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}; "
        f"{results[0]['adapter']}; final quality {results[0]['quality'].removesuffix(' (final)')}; "
        f"{SCENE_NAMES[args.scene]}, seed {args.seed}; "
        f"LP3D_KERNEL={os.environ.get('LP3D_KERNEL', '(unset)')}",
        "",
        "| budget ms | mode | rungs drawn while dragging (frames) | render ms median / p90 | frame interval "
        "ms median / p90 | window ms median | drag frames / s | release → final ms | final render ms "
        "| super-resolved still ms | bake s | load (1 min) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        rungs = ", ".join(f"{k} ({n})" for k, n in r["rungs"].items())
        bake = f"{r['bake_s']:.1f}" if r["bake_s"] is not None else "–"
        sr = f"{r['superres_ms']:.0f}" if r["superres_ms"] is not None else "–"
        lines.append(
            f"| {r['budget']:g} | {r['mode']} | {rungs} | {r['render_median']:.1f} / {r['render_p90']:.1f} | "
            f"{r['interval_median']:.1f} / {r['interval_p90']:.1f} | {r['window_median']:.1f} | "
            f"{1e3 / r['interval_median']:.1f} | "
            f"{r['release_to_final']:.0f} | {r['final_ms']:.0f} | {sr} | {bake} | {r['load']:.1f} |"
        )
    for mode in modes:
        fields = [r["field"] for r in results if r["field"] and r["mode"] == mode]
        if not fields:
            continue
        f = fields[0]
        k = f"{f['subdivisions']}" + (f" / {f['fine_subdivisions']}" if f.get("fine_subdivisions") else "")
        fine = f" ({f['fine_bricks']} fine)" if f.get("fine_subdivisions") else ""
        lines += [
            "",
            f"Baked field ({mode}): k {k}, epsilon {f['epsilon']:.0e}, {f['bricks']} bricks{fine} of "
            f"{f['cells']}³ cells, {f['device_bytes'] / 2**20:.0f} MiB; the GPU part of its bake "
            f"{statistics.median(x['bake_seconds'] for x in fields):.1f} s (median).",
        ]
    lines += [
        "",
        "First render of each rung in a process against its later renders (first run of each mode above):",
        "",
        "| rung | first render ms | median of later renders ms (count) |",
        "|---|---|---|",
    ]
    for mode in modes:
        first_run = next(r for r in results if r["mode"] == mode)
        for rung, first, later, n in first_vs_later(first_run["frames"]):
            later_s = f"{later:.1f} ({n})" if later is not None else "– (0)"
            lines.append(f"| {rung} | {first:.1f} | {later_s} |")
    lines.append("")
    args.out.write_text("\n".join(lines))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
