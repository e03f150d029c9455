"""lp3d-view end to end, in a real window under Xvfb: a scripted drag renders at the quality rung
the frame budget picks, the refined final image must equal lp3d_render.render of the same camera
and settings (both run the same kernels), once the baked field is ready a drag draws from it at
the chosen quality and the still image is exact again, and bad inputs exit non-zero with a clear
message.
Needs xvfb-run (installed by scripts/install-system-deps.sh); without it the test fails, it is
not skipped."""

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
from lp3d.images import rgb_to_uint8
from lp3d.render.camera import look_at_camera
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane

XVFB = ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24"]


def run_view(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    assert shutil.which("xvfb-run"), "xvfb-run is missing: run scripts/install-system-deps.sh"
    cmd = [*XVFB, sys.executable, "-m", "lp3d.cli", "view", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def sphere_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("view") / "sphere.npz"
    save_triplane(path, coloured_sphere(size=64))
    return path


def bilinear_upscale(image: np.ndarray, size: int) -> np.ndarray:
    """(R, R, C) -> (size, size, C) float: texture sampling at pixel centres, clamp to edge."""
    res = image.shape[0]
    coord = (np.arange(size) + 0.5) * res / size - 0.5
    lo = np.floor(coord).astype(int)
    frac = coord - lo
    i0, i1 = np.clip(lo, 0, res - 1), np.clip(lo + 1, 0, res - 1)
    img = image.astype(float)
    rows = img[i0] * (1 - frac)[:, None, None] + img[i1] * frac[:, None, None]
    return rows[:, i0] * (1 - frac)[None, :, None] + rows[:, i1] * frac[None, :, None]


def test_drag_then_refined_image_matches_render(gpu, sphere_file: Path, tmp_path: Path) -> None:
    """A scripted drag (synthetic pointer events through egui) renders at the ladder's cheapest
    rung under a budget no rung can meet, then the view refines rung by rung to the chosen
    settings; that final image, read back from its texture, equals lp3d_render.render, and the
    window shows it scaled to fit with bilinear filtering. Without the baked field (--no-bake):
    the ladder alone."""
    shot = tmp_path / "shot.png"
    yaw, pitch, res, coarse, fine, drag = 25.0, -8.0, 48, 24, 16, 6
    proc = run_view(
        *("--screenshot", str(shot), "--yaw", str(yaw), "--pitch", str(pitch)),
        *("--resolution", str(res), "--samples", f"{coarse}+{fine}"),
        *("--frame-budget-ms", "1", "--drag-frames", str(drag), "--no-bake"),
        str(sphere_file),
    )
    assert proc.returncode == 0, proc.stderr
    meta = json.loads(shot.with_suffix(".json").read_text())
    assert meta["bake"] == {"state": "off", "error": None, "job_seconds": None, "field": None}
    assert not any(f["baked"] for f in meta["frames"])
    assert meta["settings"] == {
        "resolution": res,
        "depth_resolution": coarse,
        "depth_resolution_importance": fine,
    }
    assert meta["quality"] == f"{res}² · {coarse}+{fine} (final)"
    assert meta["frame_budget_ms"] == 1

    # The frame log: every render during the drag at the cheapest rung, then one exact rung per
    # frame up to the top after the release (rungs 3 and 4, 48² · 12+8 and 18+8, are drawn only from
    # a baked field).
    frames = meta["frames"]
    dragging = [f for f in frames if f["dragging"]]
    assert len(dragging) == drag, f"expected one render per drag step, got {len(dragging)}"
    for f in dragging:
        assert (f["rung"], f["phase"]) == (0, "moving"), f
        assert (f["resolution"], f["depth_resolution"], f["depth_resolution_importance"]) == (12, 6, 4)
        assert f["render_ms"] > 0 and f["interval_ms"] > 0
    after = frames[frames.index(dragging[-1]) + 1 :]
    assert [f["rung"] for f in after] == [1, 2, 5], after
    assert [f["rungs"] for f in frames] == [6] * len(frames)
    assert after[-1]["phase"] == "final" and after[-1]["resolution"] == res
    assert meta["drag"]["frames"] == drag and meta["drag"]["release_to_final_ms"] > 0
    # The drag orbited the camera: a quarter of the view to the right is -30° of yaw.
    assert meta["yaw"] == pytest.approx(yaw - 30.0, abs=0.5) and meta["pitch"] > pitch + 5

    tri = lp3d_render.Triplane.load(sphere_file)
    camera = look_at_camera(yaw_deg=meta["yaw"], pitch_deg=meta["pitch"])
    expected = rgb_to_uint8(
        lp3d_render.render(
            tri,
            camera,
            resolution=res,
            depth_resolution=coarse,
            depth_resolution_importance=fine,
            outputs=["rgb"],
        )["rgb"]
    ).astype(int)
    rendered = np.asarray(Image.open(shot.parent / meta["render"]))
    assert rendered.shape == (res, res, 4) and (rendered[..., 3] == 255).all()
    diff = np.abs(rendered[..., :3].astype(int) - expected)
    # 8-bit quantisation in the shader vs NumPy's rounding: at most one level apart.
    assert diff.max() <= 1, (
        f"max difference {diff.max()} levels at {np.unravel_index(diff.argmax(), diff.shape)}"
    )

    view = meta["view"]
    assert view["resolution"] == res and view["scale"] == pytest.approx(view["size"] / res)
    window = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert window.shape[:2] == (meta["window"][1], meta["window"][0])
    assert view["size"] > 4 * res, "the render is scaled to fill the view"
    crop = window[view["y"] : view["y"] + view["size"], view["x"] : view["x"] + view["size"]]
    # Bilinear magnification: within 2 levels of a float64 bilinear upscale (the window's 8-bit
    # rounding, plus the sampler's fixed-point weights); a nearest-neighbour upscale is far off.
    smooth = np.abs(crop - bilinear_upscale(expected, view["size"]))
    assert smooth.max() <= 2, f"max {smooth.max():.2f} levels from a bilinear upscale"
    blocks = expected[np.arange(view["size"]) * res // view["size"]][
        :, np.arange(view["size"]) * res // view["size"]
    ]
    assert np.abs(crop - blocks).max() > 20, "the view looks nearest-filtered"
    # The controls are in the same window: the left panel is not the 3D view and not black.
    assert window[:, : view["x"] - 4].mean() > 10
    # The panels are drawn unfilled over the window's clear colour: the strip above the view is one
    # colour, the left panel's own background (its commonest colour), not eframe's near-black.
    strip = window[: view["y"], view["x"] : view["x"] + view["size"]].reshape(-1, 3)
    assert len(strip) > 0 and (strip == strip[0]).all(), "the view's surround is not one colour"
    colours, counts = np.unique(window[:, : view["x"] - 4].reshape(-1, 3), axis=0, return_counts=True)
    assert (strip[0] == colours[counts.argmax()]).all() and strip[0].mean() > 20, (
        f"surround {strip[0]} against the panel's {colours[counts.argmax()]}"
    )


def test_drag_draws_from_the_baked_field_once_it_is_ready(gpu, sphere_file: Path, tmp_path: Path) -> None:
    """The viewer bakes the file's fields in the background (the quick one, then the fine one that
    replaces it); the scripted drag starts once both are done and every drag frame is drawn from
    the fine field at the chosen resolution and fine samples with a third more coarse ones (not a
    lower rung of the ladder); after the release the still image is exact at the chosen quality."""
    shot = tmp_path / "baked.png"
    # 48 coarse samples: intervals under one baked cell, so few cells around the sphere are baked.
    res, coarse, fine, drag = 32, 48, 8, 4
    proc = run_view(
        *("--screenshot", str(shot), "--resolution", str(res), "--samples", f"{coarse}+{fine}"),
        *("--frame-budget-ms", "10000", "--drag-frames", str(drag)),
        str(sphere_file),
    )
    assert proc.returncode == 0, proc.stderr
    meta = json.loads(shot.with_suffix(".json").read_text())
    bake, field = meta["bake"], meta["bake"]["field"]
    assert bake["state"] == "ready" and bake["error"] is None, bake
    assert (field["subdivisions"], field["fine_subdivisions"]) == (4, 16), field
    assert field["epsilon"] == pytest.approx(1e-4), field
    # The index (4 bytes per cell) and (k + 1)³ points of 8 bytes per brick: 5³ in the coarse
    # bricks, 17³ in the fine ones (the sphere's surface crosses some of its bricks), which sit in
    # whole slots of a 3D texture (baked::atlas), fewer of them unused than used.
    coarse_bricks, fine_bricks = field["bricks"] - field["fine_bricks"], field["fine_bricks"]
    assert coarse_bricks > 0 and fine_bricks > 0
    fine_bytes = field["device_bytes"] - (4 * field["cells"] ** 3 + 8 * 5**3 * coarse_bricks)
    slot = 8 * 17**3
    assert fine_bytes % slot == 0 and fine_bricks <= fine_bytes // slot < 2 * fine_bricks, fine_bytes
    assert 0 < field["bake_seconds"] <= bake["job_seconds"]
    frames = meta["frames"]
    dragging = [f for f in frames if f["dragging"]]
    assert len(dragging) == drag, dragging
    for f in dragging:
        assert (f["baked"], f["bake"], f["phase"]) == (True, "ready", "moving"), f
        samples = (f["depth_resolution"], f["depth_resolution_importance"])
        assert (f["resolution"], *samples) == (res, coarse * 4 // 3, fine), f
    # Before the drag, and after the release: exact frames (the still image never comes from the field).
    before = frames[: frames.index(dragging[0])]
    assert before and not any(f["baked"] for f in before)
    after = frames[frames.index(dragging[-1]) + 1 :]
    assert [(f["baked"], f["phase"], f["resolution"]) for f in after] == [(False, "final", res)], after
    assert meta["quality"] == f"{res}² · {coarse}+{fine} (final)"
    # The window at the last moving frame, captured before the release: the baked frame on screen
    # (its panel said so). The release changes no view, so the still image that followed shows the
    # same one, exact: close to the drag image but not equal.
    drag_shot = shot.with_suffix(".drag.png")
    assert meta["drag"]["image"] == drag_shot.name
    assert meta["drag"]["image_quality"] == f"{res}² · {coarse * 4 // 3}+{fine} (moving, baked)"
    moving = np.asarray(Image.open(drag_shot).convert("RGB"), dtype=np.int16)
    still = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int16)
    assert moving.shape == still.shape
    v = meta["view"]
    view = np.s_[v["y"] : v["y"] + v["size"], v["x"] : v["x"] + v["size"]]
    assert 0.0 < np.abs(moving[view] - still[view]).mean() < 2.0, "the drag image is not the baked frame"


def test_the_still_image_of_a_shipped_model_head_is_super_resolved(gpu, tmp_path: Path) -> None:
    """``lp3d view`` of a head the shipped model lifted picks its super-resolution network: once the
    exact image is up, the viewer renders its 64² feature image and shows the network's 256² image,
    equal to ``lp3d_render.render(..., superres=)`` of the same camera and samples (to 8-bit
    rounding). ``--no-superres`` keeps the raw image as the final one; another decoder's file gets
    no network."""
    from lp3d.lift.gpu_superres import load_gpu_superres
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder

    encoder = load_encoder(DEFAULT_MODEL)
    image = np.random.default_rng(5).uniform(-1, 1, (1, 3, 128, 128)).astype(np.float32)
    head = tmp_path / "head.npz"
    save_triplane(head, encoder.package.triplane(encoder.run(image)[0]))
    shot = tmp_path / "sr.png"
    yaw, res, coarse, fine = 15.0, 32, 12, 12
    common = ("--yaw", str(yaw), "--resolution", str(res), "--samples", f"{coarse}+{fine}", "--no-bake")
    proc = run_view("--screenshot", str(shot), *common, str(head))
    assert proc.returncode == 0, proc.stderr
    meta = json.loads(shot.with_suffix(".json").read_text())
    assert meta["quality"] == f"256² super-resolved from 64² · {coarse}+{fine} (final)"
    last, before = meta["frames"][-1], meta["frames"][-2]
    assert (last["superres"], last["phase"], last["resolution"]) == (True, "final", 64), last
    # The exact image at the chosen settings came first, no longer final once the network is on.
    assert (before["superres"], before["phase"], before["resolution"]) == (False, "refining", res)
    sr = load_gpu_superres()
    camera = look_at_camera(yaw_deg=meta["yaw"], pitch_deg=meta["pitch"])
    out = lp3d_render.render(
        lp3d_render.Triplane.load(head), camera, resolution=64, depth_resolution=coarse,
        depth_resolution_importance=fine, outputs=["depth"], superres=sr,
    )  # fmt: skip
    expected = rgb_to_uint8(out["image"]).astype(int)
    rendered = np.asarray(Image.open(shot.parent / meta["render"]))
    assert rendered.shape == (256, 256, 4) and meta["view"]["resolution"] == 256
    diff = np.abs(rendered[..., :3].astype(int) - expected)
    assert diff.max() <= 1, f"max difference {diff.max()} levels"

    raw_shot = tmp_path / "raw.png"
    proc = run_view("--screenshot", str(raw_shot), *common, "--no-superres", str(head))
    assert proc.returncode == 0, proc.stderr
    raw = json.loads(raw_shot.with_suffix(".json").read_text())
    assert raw["quality"] == f"{res}² · {coarse}+{fine} (final)"
    assert not any(f["superres"] for f in raw["frames"])


def test_a_bad_superres_file_is_refused_before_the_window_opens(sphere_file: Path, tmp_path: Path) -> None:
    bad = tmp_path / "sr.npz"
    np.savez(bad, format_version=np.array(1), input_resolution=np.array(64))
    proc = run_view("--screenshot", str(tmp_path / "s.png"), "--superres", str(bad), str(sphere_file))
    assert proc.returncode == 1 and "sr.npz" in proc.stderr and "expected format_version" in proc.stderr
    assert not (tmp_path / "s.png").exists()
    both = subprocess.run(
        [sys.executable, "-m", "lp3d.cli", "view", "--superres", str(bad), "--no-superres", str(sphere_file)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert both.returncode == 2 and "not both" in both.stderr


def test_bad_inputs_exit_non_zero(tmp_path: Path) -> None:
    missing = run_view("--screenshot", str(tmp_path / "s.png"), str(tmp_path / "nope.npz"), timeout=120)
    assert missing.returncode != 0 and "nope.npz" in missing.stderr
    assert not (tmp_path / "s.png").exists()
    corrupt = tmp_path / "bad.npz"
    corrupt.write_bytes(b"not a zip at all")
    bad = run_view("--screenshot", str(tmp_path / "s.png"), str(corrupt), timeout=120)
    assert bad.returncode != 0 and "bad.npz" in bad.stderr
    no_file = subprocess.run(
        [sys.executable, "-m", "lp3d.cli", "view", "--screenshot", "x.png"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert no_file.returncode == 2 and "needs a triplane file" in no_file.stderr
    pitch = run_view("--pitch", "95", str(corrupt), timeout=120)
    assert pitch.returncode != 0 and "pitch" in pitch.stderr
    for args, name in [
        (["--drag-frames", "3", str(corrupt)], "--drag-frames"),
        (["--samples", "3+8", str(corrupt)], "samples"),
        (["--frame-budget-ms", "0", str(corrupt)], "frame-budget-ms"),
    ]:
        out = subprocess.run(
            [sys.executable, "-m", "lp3d.cli", "view", *args], capture_output=True, text=True, timeout=60
        )
        assert out.returncode != 0 and name in out.stderr, (args, out.stderr)


def test_viewer_flags_are_parsed_in_one_place() -> None:
    """``lp3d view`` hands its arguments to the viewer crate's parser (``lp3d_render.view_options``),
    the one that cargo's ``lp3d-view`` uses: same flags, same values, same help."""
    opts = lp3d_render.view_options(
        ["--yaw", "12.5", "--samples", "16+8", "--resolution", "64", "--frames", "2", "h.npz"]
    )
    assert str(opts.pop("path")) == "h.npz"
    assert opts == {
        "help": False,
        "screenshot": None,
        "yaw": 12.5,
        "pitch": 0.0,
        "resolution": 64,
        "depth_resolution": 16,
        "depth_resolution_importance": 8,
        "frame_budget_ms": 100.0,
        "frames": 2,
        "drag_frames": 0,
        "bake": True,
        "fine_field": True,
        "superres": None,
        "no_superres": False,
    }
    assert lp3d_render.view_options(["-h"])["help"] is True
    assert lp3d_render.view_options(["--no-bake", "h.npz"])["bake"] is False
    assert lp3d_render.view_options(["--no-fine-field", "h.npz"])["fine_field"] is False
    with pytest.raises(ValueError, match="unknown option --nope"):
        lp3d_render.view_options(["--nope"])
    shown = subprocess.run(
        [sys.executable, "-m", "lp3d.cli", "view", "--help"], capture_output=True, text=True, timeout=60
    )
    usage = lp3d_render.VIEW_USAGE.replace("usage: lp3d-view", "usage: lp3d view", 1)
    assert shown.returncode == 0 and shown.stdout.strip() == usage.strip()
    for flag in ("--screenshot", "--yaw", "--pitch", "--samples", "--frame-budget-ms", "--drag-frames"):
        assert flag in lp3d_render.VIEW_USAGE
    unknown = subprocess.run(
        [sys.executable, "-m", "lp3d.cli", "view", "--nope"], capture_output=True, text=True, timeout=60
    )
    assert unknown.returncode == 2 and "unknown option --nope" in unknown.stderr
