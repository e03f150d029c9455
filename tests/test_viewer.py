"""lp3d-view end to end, in a real window under Xvfb: its screenshot's 3D view must equal
lp3d_render.render of the same camera (both run the same kernels), and bad inputs exit non-zero
with a clear message. Needs xvfb-run (installed by scripts/install-system-deps.sh); without it
the test fails, it is not skipped."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import lp3d_render
from lp3d.camera import look_at_camera
from lp3d.images import rgb_to_uint8
from lp3d.sample_scenes import coloured_sphere
from lp3d.triplane_io import save_triplane

XVFB = ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24"]


def run_view(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    assert shutil.which("xvfb-run"), "xvfb-run is missing: run scripts/install-system-deps.sh"
    cmd = [*XVFB, sys.executable, "-m", "lp3d.view", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def sphere_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("view") / "sphere.npz"
    save_triplane(path, coloured_sphere(size=64))
    return path


def test_screenshot_matches_render(gpu, sphere_file: Path, tmp_path: Path) -> None:
    shot = tmp_path / "shot.png"
    yaw, pitch, res = 25.0, -8.0, 48
    proc = run_view(
        "--screenshot",
        str(shot),
        "--yaw",
        str(yaw),
        "--pitch",
        str(pitch),
        "--resolution",
        str(res),
        str(sphere_file),
    )
    assert proc.returncode == 0, proc.stderr
    meta = json.loads(shot.with_suffix(".json").read_text())
    view = meta["view"]
    assert view["resolution"] == res and view["size"] == res * view["scale"]
    window = np.asarray(Image.open(shot).convert("RGB"))
    assert window.shape[:2] == (meta["window"][1], meta["window"][0])
    crop = window[view["y"] : view["y"] + view["size"], view["x"] : view["x"] + view["size"]]
    # One ray is a scale x scale block (nearest filtering): sample the block centres.
    s = view["scale"]
    shown = crop[s // 2 :: s, s // 2 :: s][:res, :res].astype(int)

    tri = lp3d_render.Triplane.load(sphere_file)
    expected = rgb_to_uint8(
        lp3d_render.render(
            tri, look_at_camera(yaw_deg=yaw, pitch_deg=pitch), resolution=res, outputs=["rgb"]
        )["rgb"]
    ).astype(int)
    diff = np.abs(shown - expected)
    # 8-bit quantisation in the shader vs NumPy's rounding: at most one level apart.
    assert diff.max() <= 1, (
        f"max difference {diff.max()} levels at {np.unravel_index(diff.argmax(), diff.shape)}"
    )
    # The controls are in the same window: the left panel is not the 3D view and not black.
    assert window[:, : view["x"] - 4].mean() > 10


def test_bad_inputs_exit_non_zero(tmp_path: Path) -> None:
    missing = run_view("--screenshot", str(tmp_path / "s.png"), str(tmp_path / "nope.npz"), timeout=120)
    assert missing.returncode != 0 and "nope.npz" in missing.stderr
    assert not (tmp_path / "s.png").exists()
    corrupt = tmp_path / "bad.npz"
    corrupt.write_bytes(b"not a zip at all")
    bad = run_view("--screenshot", str(tmp_path / "s.png"), str(corrupt), timeout=120)
    assert bad.returncode != 0 and "bad.npz" in bad.stderr
    no_file = subprocess.run(
        [sys.executable, "-m", "lp3d.view", "--screenshot", "x.png"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert no_file.returncode == 2 and "needs a triplane file" in no_file.stderr
    pitch = run_view("--pitch", "95", str(corrupt), timeout=120)
    assert pitch.returncode != 0 and "pitch" in pitch.stderr
