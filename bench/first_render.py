"""How long a user waits for the first image: cold (empty Mesa shader cache, as on a fresh machine)
and warm (the cache filled by an earlier run), for ``lp3d_render.render``, ``lp3d demo`` and
``lp3d-view``, each in a fresh process with the default settings.

    python bench/first_render.py --out /tmp/first_render.md            # warm and cold
    python bench/first_render.py --modes warm --out /tmp/first_render.md

Times are wall-clock seconds of the whole process (interpreter start, imports, adapter, pipeline
compile, upload, render and read-back). By default (``LP3D_KERNEL`` unset) a cold process draws with
the quick kernel while the fast one compiles in the background (crates/renderer/src/kernel.rs);
the ``LP3D_KERNEL=fast`` row waits for the fast kernel instead. Cold runs point
``MESA_SHADER_CACHE_DIR`` at a new empty folder (only for ``lp3d_render.render`` by default: the
others compile the same kernels); warm runs use ``$MESA_SHADER_CACHE_DIR`` (as ``./dev`` sets it)
after one untimed run has filled it. lavapipe compiles each pipeline on
first use, so on this renderer the cold numbers are mostly LLVM's compile of the kernel.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: A fresh process's first default render (128², 48+48) of a small scene, read back to numpy.
RENDER = """
import numpy as np, lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.sample_scenes import coloured_sphere
t = coloured_sphere(size=64)
tri = t.to_native()
out = lp3d_render.render(tri, look_at_camera(yaw_deg=20.0))
assert np.isfinite(out["rgb"]).all()
"""


def _commands(work: Path) -> dict[str, tuple[list[str], dict[str, str]]]:
    """Label -> (command, extra environment)."""
    scene = work / "sphere.npz"
    if not scene.exists():
        from lp3d.render.sample_scenes import coloured_sphere
        from lp3d.render.triplane_io import save_triplane

        save_triplane(scene, coloured_sphere(size=64))
    xvfb = ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24"]
    return {
        "lp3d_render.render (128², 48+48)": ([sys.executable, "-c", RENDER], {}),
        # The fast kernel alone (no quick kernel first): its compile is what a cold Auto run hides.
        "lp3d_render.render (128², 48+48), LP3D_KERNEL=fast": (
            [sys.executable, "-c", RENDER],
            {"LP3D_KERNEL": "fast"},
        ),
        "lp3d demo (2 encodes, 12 views, orbit GIF)": (
            [sys.executable, "-m", "lp3d.cli", "demo", "--out", str(work / "demo")],
            {},
        ),
        "lp3d-view first frame (screenshot, 128²)": (
            [
                *xvfb,
                sys.executable,
                "-m",
                "lp3d.cli",
                "view",
                "--screenshot",
                str(work / "view.png"),
                str(scene),
            ],
            {},
        ),
    }


def _run(cmd: list[str], extra_env: dict[str, str], cache: Path, timeout: float) -> float:
    env = {**os.environ, **extra_env, "MESA_SHADER_CACHE_DIR": str(cache), "OMP_WAIT_POLICY": "PASSIVE"}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])} ... failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return seconds


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="markdown table to write")
    p.add_argument("--modes", default="warm,cold", help="comma list of warm, cold (default both)")
    p.add_argument(
        "--cold-for",
        default="lp3d_render.render",
        help="run cold only for the commands whose label contains this (default lp3d_render.render)",
    )
    p.add_argument("--only", default=None, help="run only the commands whose label contains this")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per run before giving up")
    args = p.parse_args(argv)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not set(modes) <= {"warm", "cold"}:
        p.error(f"--modes: warm and/or cold, got {args.modes!r}")
    if shutil.which("xvfb-run") is None:
        p.error("xvfb-run is missing: run scripts/install-system-deps.sh")

    rows = []
    with tempfile.TemporaryDirectory(prefix="lp3d-first-render-") as tmp:
        work = Path(tmp)
        commands = _commands(work)
        if args.only:
            commands = {k: v for k, v in commands.items() if args.only in k}
        warm_cache = Path(os.environ.get("MESA_SHADER_CACHE_DIR") or work / "warm-cache")
        for label, (cmd, extra_env) in commands.items():
            for mode in modes:
                if mode == "cold" and args.cold_for not in label:
                    continue
                if mode == "cold":
                    cache = Path(tempfile.mkdtemp(prefix="cold-cache-", dir=work))
                else:
                    cache = warm_cache
                    _run(cmd, extra_env, cache, args.timeout)  # fill the cache (untimed)
                load = os.getloadavg()[0]
                seconds = _run(cmd, extra_env, cache, args.timeout)
                rows.append((label, mode, seconds, load))
                print(f"{label:45s} {mode:5s} {seconds:8.1f} s  (load {load:.1f})", flush=True)

    lines = [
        f"Command: `python bench/first_render.py --modes {','.join(modes)} --out {args.out}`  ",
        f"{platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}; "
        f"VK_DRIVER_FILES={os.environ.get('VK_DRIVER_FILES', '(unset)')}",
        "",
        "| what | cache | seconds to the first image | load average (1 min) at start |",
        "|---|---|---|---|",
        *[f"| {label} | {mode} | {s:.1f} | {load:.1f} |" for label, mode, s, load in rows],
        "",
    ]
    args.out.write_text("\n".join(lines))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
