"""Resource limits, library warnings, non-finite fields and the last hostile inputs of the previous
rounds: each ends in one line that names the real cause (or a note), never a SIGBUS, a warning
line from a library, a traceback or a silent acceptance. Each test failed before."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane import TriplaneError, occupancy_checksum
from lp3d.render.triplane_io import load_triplane, save_triplane
from support.cli import run


@pytest.fixture(scope="module")
def sphere(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "sphere.npz"
    save_triplane(path, coloured_sphere(size=16, radius=0.3))
    return path


def _limited(
    argv: list[str], limit_bytes: int, which: str = "RLIMIT_FSIZE"
) -> subprocess.CompletedProcess[str]:
    """``lp3d ARGV`` in a fresh process under a file-size limit (``ulimit -f``), or the limit
    ``which`` names (``RLIMIT_AS``: ``ulimit -v``)."""
    import resource

    def limit() -> None:
        resource.setrlimit(getattr(resource, which), (limit_bytes, limit_bytes))

    cmd = [sys.executable, "-m", "lp3d.cli", *argv]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=240, preexec_fn=limit)


@pytest.mark.parametrize("command", ["render", "orbit"])
def test_a_file_size_limit_is_file_too_large_not_sigbus(sphere, tmp_path, command) -> None:
    out = tmp_path / ("view.png" if command == "render" else "orbit.gif")
    argv = [command, str(sphere), "-o", str(out), "--resolution", "16", "--samples", "4+4"]
    if command == "orbit":
        argv += ["--frames", "2"]
    done = _limited(argv, 20 << 20)  # below the 64 MiB blocks lavapipe keeps its memory in
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert "File too large" in done.stderr and "ulimit -f" in done.stderr, done.stderr
    assert not out.exists()


def test_the_viewer_under_a_file_size_limit_says_file_too_large(sphere, tmp_path) -> None:
    """The viewer makes its own device on the same driver: the same limit, the same one line."""
    shot = tmp_path / "shot.png"
    done = _limited(["view", "--screenshot", str(shot), "--resolution", "16", str(sphere)], 20 << 20)
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert "File too large" in done.stderr and "ulimit -f" in done.stderr, done.stderr
    assert not shot.exists()


@pytest.mark.parametrize("command", ["render", "encode"])
def test_a_small_address_space_limit_is_one_line_not_sigsegv(sphere, tmp_path, command) -> None:
    """Under ``ulimit -v`` 600 MiB, OpenCV's import (encode) and the GPU driver (render) died of
    SIGSEGV with no word."""
    out = tmp_path / ("view.png" if command == "render" else "head.npz")
    src = str(sphere) if command == "render" else str(_photo(tmp_path))
    done = _limited([command, src, "-o", str(out)], 600 << 20, "RLIMIT_AS")
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert "the address-space limit (ulimit -v) leaves" in done.stderr and "Traceback" not in done.stderr
    assert not out.exists()


def test_the_gpu_driver_is_not_started_without_the_address_space_it_maps(sphere) -> None:
    """``lp3d_render`` called with too little address space left for the device: an OSError (ENOMEM)
    naming the limit, where the driver's first mapping that failed was a SIGSEGV."""
    code = f"""
import errno, resource
import lp3d_render
from lp3d.render.camera import look_at_camera
with open("/proc/self/statm") as f:
    mapped = int(f.read().split()[0]) * resource.getpagesize()
resource.setrlimit(resource.RLIMIT_AS, (mapped + (300 << 20), resource.RLIM_INFINITY))
tri = lp3d_render.Triplane.load({str(sphere)!r})
try:
    lp3d_render.render(tri, look_at_camera(), resolution=16)
except OSError as e:
    print("refused", e.errno == errno.ENOMEM, e)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, (done.returncode, done.stderr)
    assert done.stdout.startswith("refused True Cannot allocate memory: the GPU driver needs"), done.stdout
    assert "ulimit -v" in done.stdout


@pytest.mark.parametrize("command", ["eval", "encode --refine"])
def test_torch_that_cannot_load_under_a_limit_is_not_called_missing(tmp_path, command) -> None:
    """PyTorch's libraries cannot be mapped under a 1.5 GiB address space: the commands said
    "needs PyTorch (pip install torch)" or "install the training extra" of an installed PyTorch."""
    if command == "eval":
        argv = ["eval", str(tmp_path / "run")]
    else:
        argv = ["encode", str(_photo(tmp_path)), "-o", str(tmp_path / "h.npz"), "--refine", "2"]
    done = _limited(argv, 3 << 29, "RLIMIT_AS")
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert "could not be loaded" in done.stderr and "pip install" not in done.stderr, done.stderr


def _photo(folder: Path) -> Path:
    """A real portrait (scikit-image's astronaut) as a JPEG in ``folder``."""
    from skimage import data

    path = folder / "astronaut.jpg"
    if not path.exists():
        Image.fromarray(data.astronaut()).save(path)
    return path


def test_a_photo_with_damaged_exif_is_a_note_not_a_warning(tmp_path) -> None:
    from lp3d.photo.load import load_image

    photo = tmp_path / "exif.jpg"
    ifd = b"II*\x00\x08\x00\x00\x00\x05\x00\x12\x01\x03\x00\x01\x00\x00\x00\x06\x00\x00\x00"
    ifd += b"\x0f\x01\x02\x00\x50\x00\x00\x00\x00\x10\x00\x00"  # a tag pointing past the end
    Image.fromarray(np.zeros((64, 64, 3), np.uint8)).save(photo, exif=b"Exif\x00\x00" + ifd)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        arr, notes = load_image(photo)
    assert arr.shape == (64, 64, 3)
    assert len(notes) == 1 and notes[0].startswith("exif.jpg: damaged metadata ignored"), notes


def test_mesh_of_planes_that_overflow_names_the_non_finite_decode(capsys, tmp_path) -> None:
    tri = coloured_sphere(size=16)
    path = tmp_path / "huge.npz"
    save_triplane(path, dataclasses.replace(tri, planes=tri.planes * np.float32(1e36)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, _, err = run(capsys, "mesh", path, "-o", tmp_path / "m.ply", "--grid", "16")
    assert code == 1 and "not finite" in err and "nan" not in err, err
    code, _, err = run(capsys, "mesh", path, "-o", tmp_path / "m.ply", "--threshold", "nan")
    assert code == 2 and "--threshold" in err


def test_mesh_export_of_large_planes_leaks_no_numpy_warning(capsys, tmp_path) -> None:
    tri = coloured_sphere(size=16)
    path = tmp_path / "strong.npz"
    save_triplane(path, dataclasses.replace(tri, planes=tri.planes * np.float32(300)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, _, err = run(capsys, "mesh", path, "-o", tmp_path / "m.glb", "--grid", "16", "--threshold", "0")
    assert code in (0, 1) and "Warning" not in err, err


def test_a_model_that_is_a_fifo_or_a_folder_is_named_as_such(capsys, sphere, tmp_path) -> None:
    from lp3d.lift.inference import load_encoder
    from lp3d.lift.model_package import ModelPackageError

    fifo = tmp_path / "model.onnx"
    os.mkfifo(fifo)
    with pytest.raises(ModelPackageError, match="model.onnx: is a FIFO"):
        load_encoder(fifo)
    folder = tmp_path / "folder.onnx"
    folder.mkdir()
    with pytest.raises(ModelPackageError, match="folder.onnx: is a folder, not an ONNX model file"):
        load_encoder(folder)
    with pytest.raises(ModelPackageError, match="is a folder; an ONNX model is a file"):
        load_encoder(folder, "onnx")


@pytest.mark.parametrize(
    ("flag", "value"), [("--tolerance", "-1"), ("--tolerance", "nan"), ("--opset", "99")]
)
def test_export_refuses_impossible_settings_when_parsing(capsys, tmp_path, flag, value) -> None:
    code, _, err = run(capsys, "export", tmp_path / "x.pt", "-o", tmp_path / "y.onnx", flag, value)
    assert code == 2 and flag in err and "Traceback" not in err, err


def test_a_grid_baked_for_other_planes_is_refused(tmp_path) -> None:
    import lp3d_render

    tri = coloured_sphere(size=16)
    path = tmp_path / "baked.npz"
    save_triplane(path, dataclasses.replace(tri, occupancy=tri.to_native().bake_occupancy(8)))
    loaded = load_triplane(path)
    assert loaded.occupancy_checksum is not None
    with pytest.raises(TriplaneError, match="occupancy: baked for other planes"):
        dataclasses.replace(loaded, planes=loaded.planes * 2)
    assert lp3d_render.Triplane.load(str(path)).occupancy is not None


def test_a_grid_of_unknown_origin_must_bound_the_planes(tmp_path) -> None:
    """A grid handed over without the checksum it was baked for is checked against a fresh bake: the
    renderer's constructor and save_triplane refuse one baked for other planes, and write nothing."""
    tri = coloured_sphere(size=16)
    own = tri.to_native().bake_occupancy(8)
    # Fainter planes: their grid is below this sphere's somewhere, so it would skip its density.
    other = dataclasses.replace(tri, planes=tri.planes * 0.3).to_native().bake_occupancy(8)
    assert (other < own).any()
    foreign = dataclasses.replace(tri, occupancy=other)
    with pytest.raises(ValueError, match=r"occupancy: not an upper bound of these planes' density: cell"):
        foreign.to_native()
    path = tmp_path / "foreign.npz"
    with pytest.raises(TriplaneError, match="occupancy: not an upper bound"):
        save_triplane(path, foreign)
    assert list(tmp_path.iterdir()) == []
    # A wrong checksum is refused; the right one, a looser grid and the grid's own bake are taken.
    with pytest.raises(ValueError, match="occupancy: baked for other planes or another decoder"):
        dataclasses.replace(tri, occupancy=own, occupancy_checksum=occupancy_checksum(tri) ^ 1)
    import lp3d_render

    weights = (tri.planes, tri.w0, tri.b0, tri.w1, tri.b1)
    with pytest.raises(ValueError, match="occupancy: baked for other planes or another decoder"):
        lp3d_render.Triplane(*weights, occupancy=own, occupancy_checksum=occupancy_checksum(tri) ^ 1)
    with pytest.raises(ValueError, match="occupancy_checksum: given without an occupancy grid"):
        lp3d_render.Triplane(*weights, occupancy_checksum=occupancy_checksum(tri))
    lp3d_render.Triplane(*weights, occupancy=own, occupancy_checksum=occupancy_checksum(tri))
    dataclasses.replace(tri, occupancy=own + 1.0).to_native()
    save_triplane(path, dataclasses.replace(tri, occupancy=own))
    assert load_triplane(path).occupancy_checksum == occupancy_checksum(tri)


def test_an_error_after_ctrl_c_is_reported_as_the_interrupt() -> None:
    """An import that Ctrl-C cut short fails as an ImportError, which the code around it reports as
    a missing package ("the onnx backend needs onnxruntime"): the command says "interrupted"."""
    script = (
        "import argparse, os, signal, sys, time\n"
        "from lp3d.errors import run_command\n"
        # Ctrl-C as from a terminal: a shell starts a background job's processes with SIGINT ignored.
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "def func(args):\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT); time.sleep(5)\n"
        "    except KeyboardInterrupt:\n"
        "        raise ValueError('the onnx backend needs onnxruntime') from None\n"
        "p = argparse.ArgumentParser(prog='lp3d x')\n"
        "p.set_defaults(func=func)\n"
        "sys.exit(run_command(p, []))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 128 + signal.SIGINT and done.stderr == "lp3d x: interrupted\n", done
