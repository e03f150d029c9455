"""Hostile values, not files: every argument of ``lp3d_render`` and every
camera flag of ``lp3d`` is refused with an error naming it and the bad value, and finite inputs that
would overflow float32 on the GPU are refused instead of rendering NaN (a black image, exit 0)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import lp3d_render
from lp3d.cli import main
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane import TriplaneData
from lp3d.render.triplane_io import save_triplane
from support.scenes import PARITY_CAMERAS, make_scene

KW = {"resolution": 5, "depth_resolution": 12, "depth_resolution_importance": 12}
FRONTAL = PARITY_CAMERAS["frontal"]


@pytest.fixture(scope="module")
def tri() -> object:
    return make_scene(size=(8, 8)).native


# ====================================================================== arguments name themselves


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        # Python ints have no size limit: PyO3 raised OverflowError naming nothing.
        ({"resolution": 2**70}, ValueError, "resolution: must be an int in [1, 1024], got int 1180591"),
        ({"resolution": -(2**70)}, ValueError, "resolution: must be an int in [1, 1024]"),
        ({"resolution": 2**20000}, ValueError, "resolution: must be an int in [1, 1024], got int of"),
        ({"depth_resolution": 2**64}, ValueError, "depth_resolution: must be an int"),
        ({"deterministic": False, "seed": 2**70}, ValueError, "seed: must be an int in [0, 4294967295]"),
        # Wrong types are TypeErrors that name the argument and show the value.
        ({"resolution": 32.0}, TypeError, "resolution: must be an int, got float 32.0"),
        ({"resolution": np.float32(32.0)}, TypeError, "resolution: must be an int, got float32"),
        ({"resolution": "32"}, TypeError, "resolution: must be an int, got str '32'"),
        ({"depth_resolution_importance": None}, TypeError, "depth_resolution_importance: must be an int"),
        # A bool is not an int here (True was rendered at resolution 1).
        ({"resolution": True}, TypeError, "resolution: must be an int, got bool True"),
        ({"resolution": np.bool_(True)}, TypeError, "resolution: must be an int, got bool"),
        ({"deterministic": False, "seed": True}, TypeError, "seed: must be an int, got bool True"),
        ({"white_back": "yes"}, TypeError, "white_back: must be a bool (True or False), got str 'yes'"),
        ({"white_back": 1}, TypeError, "white_back: must be a bool (True or False), got int 1"),
        ({"deterministic": "no"}, TypeError, "deterministic: must be a bool"),
        ({"occupancy_coarse": 1}, TypeError, "occupancy_coarse: must be a bool"),
        # A bare string was iterated as letters or refused with "Can't extract `str` to `Vec`".
        ({"outputs": "rgb"}, TypeError, "outputs: must be a list of strings such as ['rgb'], got str 'rgb'"),
        ({"outputs": ["rgb", 3]}, TypeError, "outputs: must hold strings, got int 3"),
        ({"outputs": 5}, TypeError, "outputs: must be a list of strings"),
        ({"outputs": iter(lambda: "rgb", None)}, ValueError, "outputs: holds more than 64 names"),
        ({"empty_threshold": "0"}, TypeError, "empty_threshold: must be a number, got str '0'"),
        ({"empty_threshold": False}, TypeError, "empty_threshold: must be a number, got bool False"),
        ({"transmittance_threshold": 1e300}, ValueError, "transmittance_threshold: must be finite, got"),
        ({"occupancy_epsilon": 10**400}, ValueError, "occupancy_epsilon: must be finite"),
    ],
)
def test_render_arguments_name_themselves(gpu, tri, kwargs, error, words) -> None:
    with pytest.raises(error) as e:
        lp3d_render.render(tri, FRONTAL, **{**KW, **kwargs})
    assert words in str(e.value)


def test_good_arguments_of_every_accepted_type(gpu, tri) -> None:
    """NumPy scalars, tuples and generators are as good as Python ints, bools and lists."""
    out = lp3d_render.render(
        tri,
        FRONTAL,
        resolution=np.int64(4),
        depth_resolution=np.uint8(12),
        depth_resolution_importance=12,
        deterministic=np.bool_(False),
        seed=np.int32(3),
        outputs=(name for name in ("rgb", "depth")),
        white_back=np.True_,
        empty_threshold=np.float32(0.0),
        transmittance_threshold=0,
    )
    assert set(out) == {"rgb", "depth"} and out["rgb"].shape == (3, 4, 4)


@pytest.mark.parametrize(
    ("call", "error", "words"),
    [
        (
            lambda p: lp3d_render.Triplane(*p, box_warp=True),
            TypeError,
            "box_warp: must be a number, got bool",
        ),
        (lambda p: lp3d_render.Triplane(*p, ray_end="3"), TypeError, "ray_end: must be a number, got str"),
        (lambda p: lp3d_render.Triplane(*p, box_warp=1e300), ValueError, "box_warp: must be finite"),
        (lambda p: lp3d_render.Triplane(*p).bake_occupancy(8.0), TypeError, "resolution: must be an int"),
        (
            lambda p: lp3d_render.Triplane(*p).bake_occupancy(2**70),
            ValueError,
            "resolution: must be an int in",
        ),
        (lambda p: lp3d_render.look_at_camera(yaw_deg="30"), TypeError, "yaw_deg: must be a number"),
        (lambda p: lp3d_render.look_at_camera(yaw_deg=float("inf")), ValueError, "yaw_deg: must be finite"),
        (lambda p: lp3d_render.look_at_camera(radius=1e300), ValueError, "radius: must be finite"),
        (lambda p: lp3d_render.look_at_camera(focal=True), TypeError, "focal: must be a number, got bool"),
    ],
)
def test_other_arguments_name_themselves(call, error, words) -> None:
    s = make_scene(size=(8, 8)).data
    with pytest.raises(error) as e:
        call((s.planes, s.w0, s.b0, s.w1, s.b1))
    assert words in str(e.value)


# ======================================================================= finite-output guarantee


def camera_with(index: int, value: float) -> np.ndarray:
    c = FRONTAL.astype(np.float64)
    c[index] = value
    return c


@pytest.mark.parametrize(
    ("camera", "words"),
    [
        # Finite in float64, Inf in float32: every ray became NaN and the image was empty.
        (camera_with(3, 1e300), "camera[0]: value 1e300 at index 3 (cam2world[0][3]) overflows float32"),
        (camera_with(18, -1e39), "index 18 (cx) overflows float32"),
        # Finite in float32, but the kernel's ray directions or world points would overflow it.
        (camera_with(0, 1e20), "ray directions reach"),
        (camera_with(16, 1e-30), "ray directions reach"),
        (camera_with(11, 3e38), "rays overflow float32"),
    ],
)
def test_cameras_that_overflow_float32_are_refused(gpu, tri, camera, words) -> None:
    with pytest.raises(ValueError) as e:
        lp3d_render.render(tri, camera, **KW)
    assert words in str(e.value)


def test_a_far_camera_still_renders(gpu, tri) -> None:
    out = lp3d_render.render(tri, camera_with(11, 1e30), **KW)
    assert all(np.isfinite(v).all() for v in out.values())


def scaled(data: TriplaneData, planes: float = 1.0, w1: float = 1.0) -> object:
    return lp3d_render.Triplane(
        (data.planes * planes).astype(data.planes.dtype), data.w0, data.b0, data.w1 * w1, data.b1
    )


@pytest.mark.parametrize(
    ("planes", "w1"),
    [(3e38, 1.0), (1.0, 1e37)],
    ids=["planes-3e38", "decoder-1e37"],
)
def test_triplanes_that_overflow_float32_are_refused(gpu, planes, w1) -> None:
    """The issue's planes of 3e38 rendered all-NaN: now a ValueError before any GPU work."""
    data = make_scene(size=(8, 8)).data
    data = replace(data, planes=np.sign(data.planes).astype(np.float32))
    with pytest.raises(ValueError, match=r"planes: the triplane's values overflow float32 in the decoder"):
        lp3d_render.render(scaled(data, planes, w1), FRONTAL, **KW)


def test_large_but_safe_triplanes_render_finite(gpu) -> None:
    """The bound is not a blanket cap: planes of 1e30 (far beyond any real triplane) still render,
    and every output of every ray is finite, in exact and in jittered mode."""
    data = make_scene(size=(8, 8)).data
    for factor in (1e30, 1e-30):
        out = lp3d_render.render(scaled(data, factor), np.stack([FRONTAL, camera_with(3, 0.3)]), **KW)
        assert all(np.isfinite(v).all() for v in out.values()), factor
    out = lp3d_render.render(scaled(data, 1e30), FRONTAL, **KW, deterministic=False, seed=1)
    assert all(np.isfinite(v).all() for v in out.values())


def overflowing_file(folder: Path) -> Path:
    tri = coloured_sphere(size=8)
    path = folder / "huge.npz"
    save_triplane(path, replace(tri, planes=np.full_like(tri.planes, 3e38)))
    return path


def test_cli_render_refuses_an_overflowing_triplane(gpu, capsys, tmp_path) -> None:
    """`lp3d render` wrote a black PNG and exited 0."""
    path = overflowing_file(tmp_path)
    code = main(["render", str(path), "-o", str(tmp_path / "v.png"), "--resolution", "8", "--samples", "4+4"])
    err = capsys.readouterr().err
    assert code == 1 and "huge.npz: planes: the triplane's values overflow float32" in err, err
    assert len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.npz"]


def test_viewer_refuses_an_overflowing_triplane(gpu, tmp_path) -> None:
    """lp3d-view showed black: its upload goes through the same check."""
    assert shutil.which("xvfb-run"), "xvfb-run is missing: run scripts/install-system-deps.sh"
    path = overflowing_file(tmp_path)
    shot = tmp_path / "shot.png"
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 640x480x24", sys.executable, "-m", "lp3d.cli", "view"]
    proc = subprocess.run(
        [*cmd, "--screenshot", str(shot), str(path)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode != 0 and "overflow float32" in proc.stderr, proc.stderr
    assert f"{path}: planes" in proc.stderr, proc.stderr  # the message names the file
    assert not shot.exists()


# ================================================================================ camera flags


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--yaw", "inf"], "argument --yaw: must be a finite number of degrees, got inf"),
        (["--yaw", "nan"], "argument --yaw: must be a finite number of degrees, got nan"),
        (["--yaw=-Infinity"], "argument --yaw: must be a finite number of degrees, got -Infinity"),
        (["--pitch", "nan"], "argument --pitch: must be a finite number of degrees, got nan"),
        (["--pitch", "90"], "argument --pitch: must be in (-90, 90) degrees, got 90"),
        (["--pitch=-1e300"], "argument --pitch: must be in (-90, 90) degrees, got -1e300"),
        (["--roll", "inf"], "argument --roll: must be a finite number of degrees, got inf"),
        (["--yaw", "thirty"], "argument --yaw: expected a number of degrees, got 'thirty'"),
    ],
)
@pytest.mark.parametrize("command", ["render", "orbit", "video"])
def test_camera_flags_name_themselves(capsys, tmp_path, command, argv, words) -> None:
    """`--yaw inf` failed with "math domain error" and `--yaw nan` was blamed on `camera[0]`."""
    if command == "orbit" and argv[0].startswith("--yaw"):
        return  # orbit sweeps the yaw itself: it has no --yaw
    inputs = {
        "render": ["x.npz", "-o", "v.png"],
        "orbit": ["x.npz", "-o", "o.gif"],
        "video": ["in.mp4", "-o", "o.mp4"],
    }
    code = main([command, *(str(tmp_path / a) if a != "-o" else a for a in inputs[command]), *argv])
    err = capsys.readouterr().err
    assert code == 2 and words in err, err
    assert "Traceback" not in err and not list(tmp_path.iterdir())


def test_orbit_pitch_range_must_stay_below_the_poles(capsys, tmp_path) -> None:
    sphere = tmp_path / "s.npz"
    save_triplane(sphere, coloured_sphere(size=8))
    argv = ["orbit", str(sphere), "-o", str(tmp_path / "o.gif"), "--pitch", "70", "--pitch-range", "30"]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 1 and "--pitch 70 with --pitch-range 30 leaves (-90, 90) degrees" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.npz"]


# ============================================================================== training flags


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        # --max-steps -5 was accepted and ran a minute of set-up; a huge batch ended in a MemoryError.
        (["--max-steps", "-5"], "argument --max-steps: must be in [1, 1000000000], got -5"),
        (["--max-steps", "0"], "argument --max-steps: must be in [1, "),
        (["--max-steps", "1e3"], "argument --max-steps: expected an integer, got '1e3'"),
        (["--total-steps", "-1"], "argument --total-steps: must be in [1, "),
        (["--batch", "0"], "argument --batch: must be in [1, 4096], got 0"),
        (["--batch", "100000000"], "argument --batch: must be in [1, 4096], got 100000000"),
        (["--batch", "9" * 5000], "argument --batch: expected an integer, got '999999999999"),
        (["--dataset-identities", "0"], "argument --dataset-identities: must be in [1, 1000000], got 0"),
        (["--dataset-identities", "2000000"], "argument --dataset-identities: must be in [1, 1000000]"),
        (["--checkpoint-every", "-3"], "argument --checkpoint-every: must be in [1, "),
    ],
)
@pytest.mark.parametrize("entry", ["lp3d train", "python -m lp3d.train"])
def test_training_flags_are_checked_before_any_set_up(
    capsys, monkeypatch, tmp_path, entry, argv, words
) -> None:
    import lp3d.cli.train
    from lp3d.train import main as train_main

    def set_up(args: object) -> int:
        raise AssertionError("training set-up started")

    monkeypatch.setattr(lp3d.cli.train, "run", set_up)
    full = [*argv, "--out", str(tmp_path / "run")]
    code = main(["train", *full]) if entry == "lp3d train" else train_main(full)
    err = capsys.readouterr().err
    assert code == 2 and words in err and "Traceback" not in err, err
    assert not (tmp_path / "run").exists()


# =============================================================== a machine the renderer cannot use

LAVAPIPE_HINT = "install Mesa's lavapipe (sudo apt install mesa-vulkan-drivers libvulkan1"


@pytest.mark.parametrize(
    ("env", "words"),
    [
        # No Vulkan driver: the most common first run on a new machine.
        (
            {"VK_DRIVER_FILES": "/nonexistent/lvp_icd.json", "WGPU_BACKEND": "vulkan"},
            "no GPU adapter (vulkan drivers/libraries could not be loaded; VK_DRIVER_FILES names "
            f"/nonexistent/lvp_icd.json, which does not exist): the renderer needs a Vulkan, Metal or "
            f"DirectX 12 driver; on Linux without a GPU {LAVAPIPE_HINT}",
        ),
        ({"WGPU_BACKEND": "bogus"}, "the environment variable WGPU_BACKEND='bogus' names no GPU backend"),
        ({"LP3D_KERNEL": "bogus"}, "the environment variable LP3D_KERNEL='bogus' names no renderer kernel"),
        ({"LP3D_FULL_WALK": "yes"}, "the environment variable LP3D_FULL_WALK='yes' is not 0 or 1"),
    ],
    ids=["no-vulkan-driver", "wgpu-backend", "lp3d-kernel", "lp3d-full-walk"],
)
@pytest.mark.parametrize("command", ["render", "orbit"])
def test_no_usable_gpu_is_one_line_saying_how_to_install_it(tmp_path, env, words, command) -> None:
    """Each ended in a RuntimeError traceback; the renderer starts in a fresh process, so each case runs
    in one."""
    import os

    sphere = tmp_path / "s.npz"
    save_triplane(sphere, coloured_sphere(size=8))
    out = tmp_path / ("v.png" if command == "render" else "o.gif")
    argv = [sys.executable, "-m", "lp3d.cli", command, str(sphere), "-o", str(out), "--resolution", "16"]
    if command == "orbit":
        argv += ["--frames", "2"]
    proc = subprocess.run(
        argv, capture_output=True, text=True, timeout=120, env={**os.environ, "LP3D_DEBUG": "", **env}
    )
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert last.startswith(f"lp3d {command}: error: ") and words in last, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.npz"]


def test_renderer_setup_errors_are_recognised_and_others_are_not(monkeypatch) -> None:
    """The texts lp3d_render raises (crates/renderer/src/device.rs, kernel.rs) map to one line; any other
    RuntimeError is a bug and keeps its traceback."""
    import argparse

    from lp3d.errors import renderer_setup_error, run_command

    monkeypatch.delenv("WGPU_BACKEND", raising=False)
    monkeypatch.delenv("VK_DRIVER_FILES", raising=False)
    monkeypatch.delenv("VK_ICD_FILENAMES", raising=False)
    rust = (
        "GPU error: no usable GPU adapter (No suitable graphics adapter found; noop not requested, vulkan "
        "drivers/libraries could not be loaded, gl not requested); adapters seen: []. On a machine ..."
    )
    assert renderer_setup_error(rust) == (
        "no GPU adapter (vulkan drivers/libraries could not be loaded): the renderer needs a Vulkan, Metal "
        "or DirectX 12 driver; on Linux without a GPU install Mesa's lavapipe (sudo apt install "
        "mesa-vulkan-drivers libvulkan1, or scripts/install-system-deps.sh) and set WGPU_BACKEND=vulkan"
    )
    assert renderer_setup_error("GPU error: request_device failed:\n  out of memory") == (
        "GPU error: request_device failed: out of memory"
    )
    assert renderer_setup_error("internal renderer error: index out of bounds") is None

    def fail(message: str) -> object:
        def func(args: object) -> int:
            raise RuntimeError(message)

        parser = argparse.ArgumentParser(prog="t")
        parser.set_defaults(func=func)
        return parser

    assert run_command(fail(rust), []) == 1
    with pytest.raises(RuntimeError, match="internal renderer error"):
        run_command(fail("internal renderer error: index out of bounds"), [])


def test_the_viewer_without_a_vulkan_driver_says_how_to_install_it(tmp_path) -> None:
    import os

    assert shutil.which("xvfb-run"), "xvfb-run is missing: run scripts/install-system-deps.sh"
    sphere, shot = tmp_path / "s.npz", tmp_path / "shot.png"
    save_triplane(sphere, coloured_sphere(size=8))
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 640x480x24", sys.executable, "-m", "lp3d.cli", "view"]
    env = {**os.environ, "VK_DRIVER_FILES": "/nonexistent/lvp_icd.json", "WGPU_BACKEND": "vulkan"}
    proc = subprocess.run(
        [*cmd, "--screenshot", str(shot), str(sphere)], capture_output=True, text=True, timeout=120, env=env
    )
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "lp3d view: error: no GPU adapter" in proc.stderr and LAVAPIPE_HINT in proc.stderr, proc.stderr
    assert not shot.exists()
