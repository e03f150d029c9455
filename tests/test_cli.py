"""The ``lp3d`` command line, run in-process through ``lp3d.cli.main``: every subcommand, its bad
inputs (clear one-line error, non-zero exit status, no output files left behind) and the pieces
behind it (model package, photo loading/alignment, mesh extraction and writers).

Renders are tiny (32², 12+12 samples) and the encoder is the randomly initialised ``tiny``
configuration exported to ONNX here, so the whole file runs in about a minute on two cores.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.cli import main
from lp3d.lift.model_package import ModelPackageError, load_model_package, save_model_package
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import load_triplane, save_triplane
from tiny_model import tiny_onnx_package

SMALL = ["--resolution", "32", "--samples", "12+12"]
SPHERE_RADIUS = 0.3


# =========================================================================================== fixtures


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    """``lp3d ARGV`` in-process: (exit status, stdout, stderr)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def listing(folder: Path) -> set[str]:
    """Every name in ``folder`` (temporary files included: they start with a dot)."""
    return {p.name for p in folder.iterdir()}


@pytest.fixture(scope="module")
def sphere(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small sample triplane (a coloured sphere of radius 0.3) as a .npz file."""
    path = tmp_path_factory.mktemp("scene") / "sphere.npz"
    save_triplane(path, coloured_sphere(size=32, radius=SPHERE_RADIUS))
    return path


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A randomly initialised ``tiny`` encoder: ONNX + sidecar, an export-style checkpoint and a
    training-style checkpoint, all with the sphere's decoder."""
    import torch

    folder = tmp_path_factory.mktemp("model")
    onnx_path, enc, tri, bounds = tiny_onnx_package(folder)
    decoder = {k: torch.from_numpy(getattr(tri, k)) for k in ("w0", "b0", "w1", "b1")}
    plain = folder / "tiny.pt"
    torch.save(
        {"config": enc.config.to_dict(), "encoder": enc.state_dict(), "decoder": decoder, "bounds": bounds},
        plain,
    )
    # The layout python -m lp3d.train writes: JSON configs, one 'student' state dict with prefixes.
    student = {f"encoder.{k}": v for k, v in enc.state_dict().items()}
    student.update({f"decoder.{k}": v for k, v in decoder.items()})
    train = folder / "step-000010.pt"
    torch.save(
        {
            "format": "lp3d-train-checkpoint-v1",
            "config": json.dumps({"encoder": enc.config.to_dict()}),
            "scene": json.dumps(bounds),
            "student": student,
        },
        train,
    )
    return {"onnx": onnx_path, "pt": plain, "train": train, "folder": folder}


@pytest.fixture(scope="module")
def photos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Test photos: a face (skimage's astronaut), a face-free image and assorted bad files."""
    from skimage.data import astronaut

    folder = tmp_path_factory.mktemp("photos")
    face = astronaut()
    out = {"face": folder / "face.jpg", "face_crop": folder / "face_crop.png"}
    Image.fromarray(face).save(out["face"], quality=92)
    Image.fromarray(face[:300, 80:380]).save(out["face_crop"])
    rng = np.random.default_rng(0)
    out["noface"] = folder / "noface.png"
    Image.fromarray(np.broadcast_to(np.linspace(40, 200, 256, dtype=np.uint8), (256, 256))).convert(
        "RGB"
    ).save(out["noface"])
    out["grey"] = folder / "grey.png"
    Image.fromarray(face[:300, 80:380].mean(axis=2).astype(np.uint8)).save(out["grey"])
    out["rgba"] = folder / "rgba.png"
    rgba = np.concatenate([face[:300, 80:380], np.full((300, 300, 1), 200, np.uint8)], axis=2)
    Image.fromarray(rgba, "RGBA").save(out["rgba"])
    out["text"] = folder / "notes.jpg"
    out["text"].write_text("this is not an image\n")
    out["empty"] = folder / "empty.png"
    out["empty"].write_bytes(b"")
    out["truncated"] = folder / "truncated.jpg"
    out["truncated"].write_bytes(out["face"].read_bytes()[:2000])
    out["noise"] = folder / "noise.png"
    Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(out["noise"])
    # A PNG whose header claims 12000 x 12000 pixels (144 MP): rejected before any pixel is decoded.
    out["huge"] = folder / "huge.png"
    ihdr = struct.pack(">IIBBBBB", 12000, 12000, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    out["huge"].write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", 13)
        + chunk
        + struct.pack(">I", zlib.crc32(chunk))
        + struct.pack(">I", 0)
        + b"IEND"
        + struct.pack(">I", zlib.crc32(b"IEND"))
    )
    return out


@pytest.fixture()
def bad_npz(tmp_path: Path, sphere: Path) -> dict[str, Path]:
    """A corrupt (random bytes), a truncated and an empty .npz."""
    out = {
        "garbage": tmp_path / "garbage.npz",
        "truncated": tmp_path / "truncated.npz",
        "empty": tmp_path / "e.npz",
    }
    out["garbage"].write_bytes(np.random.default_rng(1).integers(0, 255, 4000, dtype=np.uint8).tobytes())
    out["truncated"].write_bytes(sphere.read_bytes()[:3000])
    out["empty"].write_bytes(b"")
    return out


# =============================================================================================== main


def test_help_for_every_command(capsys) -> None:
    code, out, _ = run(capsys, "--help")
    assert code == 0
    commands = (
        "encode",
        "render",
        "orbit",
        "mesh",
        "share",
        "info",
        "video",
        "view",
        "demo",
        "train",
        "eval",
        "export",
    )
    for cmd in commands:
        assert cmd in out
        code, out_cmd, _ = run(capsys, cmd, "--help")
        assert code == 0 and out_cmd.startswith(f"usage: lp3d {cmd}"), cmd


def test_train_eval_export_are_the_module_commands() -> None:
    """``lp3d train|eval|export|superres-fit`` take ``python -m lp3d.train|eval|export|superres_fit``'s
    options (one definition)."""
    import argparse

    import lp3d.cli.eval
    import lp3d.cli.export
    import lp3d.cli.superres_fit
    import lp3d.cli.train
    from lp3d.cli import build_parser

    def options(parser: argparse.ArgumentParser) -> list[tuple[object, ...]]:
        return [(a.dest, tuple(a.option_strings), a.default, a.nargs, a.choices) for a in parser._actions]

    for name, module in (
        ("train", lp3d.cli.train),
        ("eval", lp3d.cli.eval),
        ("export", lp3d.cli.export),
        ("superres-fit", lp3d.cli.superres_fit),
    ):
        (sub,) = [a for a in build_parser(name)._actions if isinstance(a, argparse._SubParsersAction)]
        ours, theirs = sub.choices[name], module.build_parser()
        assert len(options(theirs)) > 3 and options(ours) == options(theirs), name
        assert ours.description == theirs.description and ours.prog == f"lp3d {name}"


@pytest.mark.parametrize(
    "module, prog",
    [
        ("lp3d.train", "python -m lp3d.train"),
        ("lp3d.export", "python -m lp3d.export"),
        ("lp3d.superres_fit", "python -m lp3d.superres_fit"),
    ],
)
def test_the_library_commands_run_with_python_m(module: str, prog: str) -> None:
    """The entry points README names for the torch commands (lp3d/train.py or a package's __main__)."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=180
    )
    assert done.returncode == 0 and done.stdout.startswith(f"usage: {prog}"), done.stderr


def test_a_closed_stdout_is_no_error_message(tmp_path) -> None:
    """``lp3d info x.npz | head -1``: when the reader goes away, the command stops with status 1 and
    prints nothing (no "Broken pipe" line, no traceback at exit)."""
    import subprocess
    import sys

    script = (
        "import argparse, sys\n"
        "from lp3d.errors import run_command\n"
        "def func(args):\n"
        "    raise BrokenPipeError(32, 'Broken pipe')\n"
        "p = argparse.ArgumentParser(prog='lp3d x')\n"
        "p.set_defaults(func=func)\n"
        "sys.exit(run_command(p, []))\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and out.stderr == "", out


def test_one_exit_code_policy_for_every_entry_point(capsys, tmp_path) -> None:
    """0 ok, 1 a runtime error (one line, no traceback), 2 a usage error: in ``lp3d`` and in the
    ``python -m lp3d.train|export`` and ``lp3d.cli.eval.main`` alike."""
    from lp3d.cli.eval import main as eval_main
    from lp3d.cli.export import main as export_main
    from lp3d.train import main as train_main

    missing = tmp_path / "missing.pt"
    for argv in (["export", missing, "-o", tmp_path / "y.onnx"], ["eval", missing, "--baseline-steps", "0"]):
        code, _, err = run(capsys, *argv)
        assert code == 1 and "no such file" in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert export_main([str(missing), "-o", str(tmp_path / "y.onnx")]) == 1
    assert eval_main([str(missing)]) == 1
    assert train_main(["--dist-timeout", "-1"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--dist-timeout must be a positive number" in err
    # Usage errors, found by argparse or after it (flags that exclude each other).
    usage = (
        ["export"],  # neither a checkpoint nor --package
        ["export", missing],  # no -o
        ["export", missing, "-o", "x.onnx", "--superres", "a.pt", "--no-superres"],
        ["eval", missing, "--n-identities", "0"],
        ["train", "--config", "no-such-config"],
    )
    for argv in usage:
        code, _, err = run(capsys, *argv)
        assert code == 2 and err.startswith("usage: lp3d ") and f"lp3d {argv[0]}: error:" in err, (argv, err)
    assert export_main([]) == 2 and eval_main(["x.pt", "--n-identities", "0"]) == 2
    assert train_main(["--config", "no-such-config"]) == 2
    assert not list(tmp_path.iterdir())


def test_python_m_lp3d_cli_and_the_import_graph(tmp_path) -> None:
    """``python -m lp3d.cli`` is ``lp3d``; importing the command line loads no torch (train, eval and
    export import it only when named); and no library module imports the command line."""
    import ast
    import os
    import subprocess
    import sys

    import lp3d

    code = "import sys, lp3d.cli; assert 'torch' not in sys.modules; sys.exit(lp3d.cli.main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, "info", str(tmp_path / "no.npz")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1 and done.stderr == f"lp3d info: error: {tmp_path / 'no.npz'}: no such file\n"
    done = subprocess.run(
        [sys.executable, "-m", "lp3d.cli", "--version"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.startswith("lp3d "), done.stderr

    root = Path(lp3d.__file__).parent
    offenders = []
    for path in root.rglob("*.py"):
        # A package's __main__.py (python -m lp3d.superres_fit) and lp3d/train.py (python -m lp3d.train)
        # are entry points: they run the command line.
        if root / "cli" in path.parents or path.name == "__main__.py" or path == root / "train.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [f"{node.module}.{a.name}" for a in node.names]
                if isinstance(node, ast.ImportFrom) and node.module
                else []
            )
            if any(n == "lp3d.cli" or n.startswith("lp3d.cli.") for n in names):
                offenders.append(os.path.relpath(path, root))
    assert not offenders, f"library modules importing lp3d.cli: {offenders}"


def test_usage_errors_exit_2(capsys, sphere) -> None:
    assert (
        run(
            capsys,
        )[0]
        == 2
    )  # no command
    assert run(capsys, "frobnicate")[0] == 2
    code, _, err = run(capsys, "render", sphere, "-o", "x.png", "--samples", "12+x")
    assert code == 2 and "COARSE+FINE" in err
    assert run(capsys, "render", sphere)[0] == 2  # -o is required
    assert run(capsys, "render", sphere, "-o", "x.png", "--features-channel", "32")[0] == 2


# ============================================================================================= render


def test_render_rgb_and_depth(capsys, sphere, tmp_path) -> None:
    view, depth = tmp_path / "view.png", tmp_path / "depth.png"
    code, out, err = run(
        capsys, "render", sphere, "--yaw", 30, "--pitch", -10, *SMALL, "-o", view, "--depth", depth
    )
    assert code == 0, err
    assert "wrote" in out and listing(tmp_path) == {"view.png", "depth.png"}
    rgb = np.asarray(Image.open(view))
    assert rgb.shape == (32, 32, 3)
    assert rgb[16, 16].astype(int).sum() > rgb[0, 0].astype(int).sum() + 60  # the sphere on a dark background
    assert np.asarray(Image.open(depth)).shape == (32, 32, 3)


def test_render_feature_channel(capsys, sphere, tmp_path) -> None:
    code, _, err = run(capsys, "render", sphere, *SMALL, "--features-channel", 1, "-o", tmp_path / "f.png")
    assert code == 0, err
    assert np.asarray(Image.open(tmp_path / "f.png")).shape == (32, 32)


@pytest.mark.parametrize("which", ["garbage", "truncated", "empty", "missing"])
def test_render_bad_triplane(capsys, bad_npz, tmp_path, which) -> None:
    src = bad_npz.get(which, tmp_path / "missing.npz")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, out, err = run(capsys, "render", src, *SMALL, "-o", out_dir / "v.png")
    assert code == 1
    assert err.startswith("lp3d render: error:") and str(src) in err and "Traceback" not in err
    assert listing(out_dir) == set()


def test_render_bad_outputs(capsys, sphere, tmp_path) -> None:
    (tmp_path / "file.txt").write_text("x")
    cases = [
        (tmp_path / "view.bmp", "unsupported format"),
        (tmp_path / "nowhere" / "view.png", "does not exist"),
        (tmp_path / "file.txt" / "view.png", "not a folder"),
        (tmp_path, "unsupported format"),
    ]
    for target, words in cases:
        code, _, err = run(capsys, "render", sphere, *SMALL, "-o", target)
        assert code == 1 and words in err, (target, err)
    # Passes the up-front checks as root, then fails to create the file: still one clear line.
    code, _, err = run(capsys, "mesh", sphere, "--grid", 8, "-o", "/proc/lp3d-test.glb")
    assert code == 1 and "/proc" in err and ".tmp" not in err, err
    code, _, err = run(capsys, "render", sphere, *SMALL, "--pitch", 95, "-o", tmp_path / "v.png")
    assert code == 2 and "argument --pitch: must be in (-90, 90) degrees, got 95" in err  # a usage error
    assert listing(tmp_path) == {"file.txt"}


# ============================================================================================== orbit


def test_orbit_gif_and_mp4(capsys, sphere, tmp_path) -> None:
    import imageio.v3 as iio
    import imageio_ffmpeg

    gif, mp4 = tmp_path / "orbit.gif", tmp_path / "orbit.mp4"
    code, out, err = run(capsys, "orbit", sphere, "-o", gif, "--frames", 4, "--yaw-range", 30, *SMALL)
    assert code == 0, err
    assert "orbit" in err  # the progress bar
    frames = iio.imread(gif, index=None)
    assert frames.shape[:3] == (4, 32, 32)
    code, out, err = run(capsys, "orbit", sphere, "-o", mp4, "--frames", 3, "--batch", 2, *SMALL)
    assert code == 0, err
    reader = imageio_ffmpeg.read_frames(str(mp4))
    meta = next(reader)
    assert meta["size"] == (32, 32) and sum(1 for _ in reader) == 3
    assert listing(tmp_path) == {"orbit.gif", "orbit.mp4"}


def test_orbit_baked_bakes_once_and_stays_close_to_exact(capsys, sphere, tmp_path) -> None:
    """``lp3d orbit --baked`` bakes before the first frame (and says so) and renders every frame by
    lookups; its frames stay close to the exact ones (the error is measured in bench/baked.py)."""
    import imageio.v3 as iio

    exact, baked = tmp_path / "exact.gif", tmp_path / "baked.gif"
    code, _, err = run(capsys, "orbit", sphere, "-o", exact, "--frames", 2, "--raw", *SMALL)
    assert code == 0, err
    code, out, err = run(capsys, "orbit", sphere, "-o", baked, "--frames", 2, "--raw", "--baked", *SMALL)
    assert code == 0 and "baked the field in" in out and "bricks" in out, err
    a, b = (iio.imread(p, index=None).astype(float) for p in (exact, baked))
    assert a.shape == b.shape and a.shape[1:] == (32, 32, 3)  # a GIF keeps one of equal frames
    assert np.abs(a - b).mean() < 4.0  # gray levels of 255


def test_orbit_baked_auto_bakes_only_when_it_pays_and_stays_within_the_bound(
    capsys, sphere, tmp_path
) -> None:
    """``--baked auto``: a raw orbit of enough frames bakes, checks its first frame against the exact
    one and keeps the field when within ``--baked-bound``; a short orbit or an unreachable bound
    renders exactly (each says why); the frames match the chosen mode's. The default stays exact."""
    import imageio.v3 as iio

    from lp3d.render.settings import bake_pays_after

    n = bake_pays_after(12, 12)  # SMALL's samples: a bake pays later than at 48+48
    assert n == 60 and bake_pays_after(48, 48) == 15 and bake_pays_after(64, 0) == 23
    paths = {name: tmp_path / f"{name}.gif" for name in ("auto", "on", "exact", "strict", "short")}

    def orbit(name: str, *flags: object, frames: int = n) -> str:
        code, out, err = run(
            capsys, "orbit", sphere, "-o", paths[name], "--frames", frames, "--raw", *flags, *SMALL
        )
        assert code == 0, err
        return out

    out = orbit("auto", "--baked", "auto")
    found = re.search(r"baked frames: the first is ([0-9.]+) dB from the exact one \(bound 40 dB\)", out)
    assert found and "baked the field in" in out, out
    score = float(found[1])
    assert 40.0 <= score < 100.0
    out = orbit("on", "--baked")
    assert "baked the field in" in out and "bound" not in out
    out = orbit("exact")  # the default: exact frames, no bake
    assert "baked the field" not in out and "baked frames" not in out
    bound = f"{score + 1:.0f}"  # just above what the field reaches: exact frames, and why
    out = orbit("strict", "--baked", "auto", "--baked-bound", bound)
    assert f"exact frames: the first baked frame is {score:.1f} dB" in out and f"({bound} dB" in out
    out = orbit("short", "--baked", "auto", frames=n - 1)
    assert f"exact frames: {n - 1} are fewer than a bake pays for ({n}" in out
    assert "baked the field in" not in out
    frames = {name: iio.imread(p, index=None) for name, p in paths.items()}
    assert np.array_equal(frames["auto"], frames["on"]) and np.array_equal(frames["strict"], frames["exact"])
    assert not np.array_equal(frames["auto"], frames["exact"])
    code, _, err = run(capsys, "orbit", sphere, "-o", paths["on"], "--baked-bound", "5", *SMALL)
    assert code == 2 and "--baked-bound" in err
    # With super-resolution (not --raw) the field cannot serve the frames: exact, and why.
    from argparse import Namespace

    from lp3d.cli.orbit import auto_baked
    from lp3d.render.settings import Skips

    args = Namespace(samples=(48, 48), baked_bound=40.0)
    assert auto_baked(args, None, object(), np.zeros((36, 25)), 256) == Skips()
    assert "exact frames: the super-resolution network reads all 32 features" in capsys.readouterr().out


def test_orbit_bad_inputs(capsys, sphere, bad_npz, tmp_path) -> None:
    code, _, err = run(capsys, "orbit", sphere, "-o", tmp_path / "o.avi", *SMALL)
    assert code == 1 and ".mp4" in err
    code, _, err = run(capsys, "orbit", bad_npz["garbage"], "-o", tmp_path / "o.gif", *SMALL)
    assert code == 1 and "garbage.npz" in err
    assert not (tmp_path / "o.gif").exists() and not list(tmp_path.glob(".o.gif*"))


# =============================================================================================== mesh


def _read_glb(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    doc = json.loads(data[20 : 20 + json_len])
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0
    binary = data[28 + json_len : 28 + json_len + bin_len]
    assert 28 + json_len + bin_len == len(data)
    return doc, binary


def test_mesh_glb_structure_and_geometry(capsys, sphere, tmp_path) -> None:
    glb = tmp_path / "head.glb"
    code, out, err = run(capsys, "mesh", sphere, "-o", glb, "--grid", 40)
    assert code == 0, err
    doc, binary = _read_glb(glb)
    assert doc["asset"]["version"] == "2.0"
    prim = doc["meshes"][0]["primitives"][0]
    assert set(prim["attributes"]) == {"POSITION", "NORMAL", "COLOR_0"} and prim["mode"] == 4
    assert doc["buffers"][0]["byteLength"] == len(binary)

    def accessor(i: int) -> np.ndarray:
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        assert view["byteOffset"] % 4 == 0 and view["byteOffset"] + view["byteLength"] <= len(binary)
        dtype = {5126: "<f4", 5125: "<u4"}[acc["componentType"]]
        width = {"VEC3": 3, "SCALAR": 1}[acc["type"]]
        arr = np.frombuffer(binary, dtype, acc["count"] * width, view["byteOffset"])
        return arr.reshape(acc["count"], width) if width > 1 else arr

    pos = accessor(prim["attributes"]["POSITION"])
    normals = accessor(prim["attributes"]["NORMAL"])
    colors = accessor(prim["attributes"]["COLOR_0"])
    tris = accessor(prim["indices"]).reshape(-1, 3)
    acc = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose(acc["min"], pos.min(axis=0), rtol=1e-6)
    np.testing.assert_allclose(acc["max"], pos.max(axis=0), rtol=1e-6)
    assert tris.max() < len(pos) and len(colors) == len(pos)
    assert colors.min() >= 0.0 and colors.max() <= 1.0
    # The sphere of radius 0.3, with outward normals and counter-clockwise (outward) triangles.
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), SPHERE_RADIUS, atol=0.02)
    assert np.mean(np.sum(normals * pos, axis=1) > 0) > 0.99
    face_n = np.cross(pos[tris[:, 1]] - pos[tris[:, 0]], pos[tris[:, 2]] - pos[tris[:, 0]])
    assert np.mean(np.sum(face_n * pos[tris].mean(axis=1), axis=1) > 0) > 0.99


def test_mesh_ply_and_obj(capsys, sphere, tmp_path) -> None:
    for name, extra in (("b.ply", []), ("a.ply", ["--ascii"]), ("m.obj", [])):
        code, out, err = run(capsys, "mesh", sphere, "-o", tmp_path / name, "--grid", 24, *extra)
        assert code == 0, err
    binary, ascii_ = (tmp_path / "b.ply").read_bytes(), (tmp_path / "a.ply").read_text()
    assert b"format binary_little_endian 1.0" in binary and "format ascii 1.0" in ascii_
    header, _, body = ascii_.partition("end_header\n")
    n_vert = int(header.split("element vertex ")[1].split()[0])
    n_face = int(header.split("element face ")[1].split()[0])
    rows = body.splitlines()
    # x y z nx ny nz red green blue alpha (trimesh writes an alpha of 255).
    assert len(rows) == n_vert + n_face and len(rows[0].split()) == 10 and rows[-1].startswith("3 ")
    # Binary body: 28 bytes per vertex (6 floats, 4 uchars) and 13 per face.
    bheader, _, bbody = binary.partition(b"end_header\n")
    assert len(bbody) == 28 * n_vert + 13 * n_face
    obj = (tmp_path / "m.obj").read_text().splitlines()
    v = [ln.split() for ln in obj if ln.startswith("v ")]
    f = [ln for ln in obj if ln.startswith("f ")]
    assert len(v) == n_vert and len(f) == n_face and len(v[0]) == 7  # x y z r g b


def test_mesh_bad_inputs(capsys, sphere, bad_npz, tmp_path) -> None:
    code, _, err = run(capsys, "mesh", sphere, "-o", tmp_path / "m.glb", "--grid", 16, "--threshold", 1e6)
    assert code == 1 and "no surface at threshold" in err
    code, _, err = run(capsys, "mesh", sphere, "-o", tmp_path / "m.stl")
    assert code == 1 and "unsupported format" in err
    code, _, err = run(capsys, "mesh", bad_npz["truncated"], "-o", tmp_path / "m.glb", "--grid", 16)
    assert code == 1 and "truncated.npz" in err
    assert listing(tmp_path) == {p.name for p in bad_npz.values()}


def test_density_grid_matches_reference(sphere) -> None:
    from lp3d.render.mesh import density_grid
    from lp3d.render.reference import decode, sample_triplane

    tri = load_triplane(sphere)
    grid = density_grid(tri, 20)
    idx = np.random.default_rng(0).integers(0, 20, (200, 3))
    points = np.linspace(-0.5, 0.5, 20)[idx]
    ref, _ = decode(
        sample_triplane(tri.planes, points, box_warp=tri.box_warp), tri.w0, tri.b0, tri.w1, tri.b1
    )
    np.testing.assert_allclose(grid[idx[:, 0], idx[:, 1], idx[:, 2]], ref, rtol=1e-4, atol=1e-4)


# =============================================================================================== info


def test_info_text_and_json(capsys, sphere, bad_npz, tmp_path) -> None:
    code, out, err = run(capsys, "info", sphere)
    assert code == 0, err
    for words in (
        "(3, 32, 32, 32) float32",
        "format_version 1",
        "w0 (64, 32)",
        "box_warp 1",
        "2.25",
        "3.3",
        "coloured_sphere",
        "occupancy:",
        "camera:",
        "KiB",
    ):
        assert words in out, words
    code, out, _ = run(capsys, "info", sphere, "--json")
    info = json.loads(out)
    assert info["planes"]["shape"] == [3, 32, 32, 32] and info["format_version"] == 1
    assert info["file_size"] == sphere.stat().st_size
    code, _, err = run(capsys, "info", bad_npz["garbage"])
    assert code == 1 and "not a valid .npz" in err
    # Not a regular file: an error naming what it is, at once (it used to say "empty file", or hang).
    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    for special, what in ((fifo, "FIFO"), (Path("/dev/zero"), "character device")):
        code, _, err = run(capsys, "info", special)
        assert code == 1 and what in err and str(special) in err and "empty" not in err


# ============================================================================================= encode


def test_encode_onnx_single_photo(capsys, model, photos, tmp_path) -> None:
    out = tmp_path / "head.npz"
    code, stdout, err = run(
        capsys, "encode", photos["face"], "-o", out, "--model", model["onnx"], "--save-crop"
    )
    assert code == 0, err
    assert "face" in stdout and "roll" in stdout and "encode" in stdout and "s/image" in stdout
    tri = load_triplane(out)
    pkg = load_model_package(model["onnx"])
    assert tri.planes.shape == (3, 32, 64, 64) and tri.planes.dtype == np.float32
    np.testing.assert_array_equal(tri.w1, pkg.w1)
    assert tri.box_warp == pkg.box_warp and "face.jpg" in (tri.source or "")
    crop = np.asarray(Image.open(tmp_path / "head.crop.png"))
    assert crop.shape == (128, 128, 3)
    assert listing(tmp_path) == {"head.npz", "head.crop.png"}


def test_encode_refine_fits_the_head_to_its_photo(capsys, model, photos, tmp_path) -> None:
    """``--refine N`` (issue 21): N steps of the torch fit after the ONNX encoder; the file records
    them, keeps the package's decoder and differs from the feed-forward planes."""
    plain, refined = tmp_path / "plain.npz", tmp_path / "refined.npz"
    common = ("--model", model["onnx"], "--no-detect")
    code, _, err = run(capsys, "encode", photos["face"], "-o", plain, *common)
    assert code == 0, err
    code, stdout, err = run(capsys, "encode", photos["face"], "-o", refined, *common, "--refine", 2)
    assert code == 0, err
    assert "refined 2 steps" in stdout and "input view" in stdout and "refine" in stdout
    a, b = load_triplane(plain), load_triplane(refined)
    assert "refined 2 steps" in (b.source or "") and b.camera is not None
    np.testing.assert_array_equal(a.w0, b.w0)
    assert not np.array_equal(a.planes, b.planes)
    code, _, err = run(capsys, "encode", photos["face"], "-o", refined, *common, "--refine", -1)
    assert code == 2 and "--refine" in err


def test_encode_flip_average_is_the_mean_of_the_photo_and_its_mirror(capsys, model, photos, tmp_path) -> None:
    """``--flip-average``: the written planes are ``LoadedEncoder.encode(crop, flip_average=True)`` of
    the crop it saved, which differs from the plain encoding (the random encoder is not symmetric)."""
    from lp3d.lift.inference import load_encoder
    from lp3d.photo import to_encoder_input

    plain, flipped = tmp_path / "plain.npz", tmp_path / "flipped.npz"
    common = ("--model", model["onnx"], "--no-detect")
    code, _, err = run(capsys, "encode", photos["face_crop"], "-o", plain, *common)
    assert code == 0, err
    code, stdout, err = run(
        capsys, "encode", photos["face_crop"], "-o", flipped, *common, "--flip-average", "--save-crop"
    )
    assert code == 0, err
    assert "flip-averaged" in stdout
    tri = load_triplane(flipped)
    assert "flip-averaged" in (tri.source or "")
    crop = np.asarray(Image.open(tmp_path / "flipped.crop.png"))
    want = load_encoder(model["onnx"]).encode(to_encoder_input(crop[None]), flip_average=True)[0]
    np.testing.assert_allclose(tri.planes, want, rtol=0, atol=1e-6)
    assert np.abs(tri.planes - load_triplane(plain).planes).max() > 1e-3


def test_encode_and_the_python_api_write_the_same_permissions(capsys, model, photos, tmp_path) -> None:
    """``lp3d encode`` and ``save_triplane`` publish through one writer (lp3d.atomic): the outputs get
    the mode of any new file, ``0666 & ~umask``. The umask 027 is unusual on purpose: its 0640 is
    neither mkstemp's 0600 nor the common 0644."""
    old = os.umask(0o027)
    try:
        out = tmp_path / "cli.npz"
        code, _, err = run(
            capsys,
            "encode",
            photos["face_crop"],
            "-o",
            out,
            "--model",
            model["onnx"],
            "--no-detect",
            "--save-crop",
        )
        assert code == 0, err
        save_triplane(tmp_path / "api.npz", load_triplane(out))
    finally:
        os.umask(old)
    modes = {p.name: oct(stat.S_IMODE(p.stat().st_mode)) for p in tmp_path.iterdir()}
    assert modes == {name: oct(0o640) for name in ("cli.npz", "cli.crop.png", "api.npz")}


def test_encode_folder_batch_and_torch_backends(capsys, model, photos, tmp_path) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    shutil.copy(photos["face"], folder / "a.jpg")
    shutil.copy(photos["face_crop"], folder / "b.png")
    (folder / "readme.txt").write_text("not a photo; ignored by the folder scan")
    outdir = tmp_path / "out"
    code, _, err = run(capsys, "encode", folder, "-o", outdir, "--model", model["onnx"], "--batch-size", 2)
    assert code == 0, err
    assert listing(outdir) == {"a.npz", "b.npz"}
    onnx_planes = load_triplane(outdir / "a.npz").planes
    # Torch, both checkpoint layouts: the same planes as ONNX Runtime.
    for key in ("pt", "train"):
        dest = tmp_path / f"{key}.npz"
        code, stdout, err = run(
            capsys, "encode", folder / "a.jpg", "-o", dest, "--model", model[key], "--half"
        )
        assert code == 0, err
        tri = load_triplane(dest)
        assert tri.planes.dtype == np.float16 and "torch" in stdout
        np.testing.assert_allclose(tri.planes.astype(np.float32), onnx_planes, atol=5e-3, rtol=5e-3)


def test_encode_conversions_and_no_detect(capsys, model, photos, tmp_path) -> None:
    code, _, err = run(capsys, "encode", photos["grey"], "-o", tmp_path / "g.npz", "--model", model["onnx"])
    assert code == 0 and "warning:" in err and "grayscale" in err
    code, _, err = run(capsys, "encode", photos["rgba"], "-o", tmp_path / "r.npz", "--model", model["onnx"])
    assert code == 0 and "alpha" in err
    code, out, err = run(
        capsys, "encode", photos["noise"], "-o", tmp_path / "n.npz", "--model", model["onnx"], "--no-detect"
    )
    assert code == 0 and "no detection" in out, err
    assert listing(tmp_path) == {"g.npz", "r.npz", "n.npz"}


@pytest.mark.parametrize(
    ("photo", "words"),
    [
        ("noface", "--no-detect"),
        ("text", "not an image"),
        ("empty", "empty file"),
        ("truncated", "truncated"),
        ("huge", "MP limit"),
    ],
)
def test_encode_bad_photos(capsys, model, photos, tmp_path, photo, words) -> None:
    code, _, err = run(capsys, "encode", photos[photo], "-o", tmp_path / "x.npz", "--model", model["onnx"])
    assert code == 1 and words in err and err.startswith("lp3d encode: error:"), err
    assert listing(tmp_path) == set()


def test_encode_one_bad_photo_fails_the_batch(capsys, model, photos, tmp_path) -> None:
    outdir = tmp_path / "out"
    code, _, err = run(
        capsys, "encode", photos["face"], photos["noface"], "-o", outdir, "--model", model["onnx"]
    )
    assert code == 1 and "noface.png" in err
    assert listing(tmp_path) == set()  # the output folder it would have created is gone too


def test_encode_large_photo_is_downscaled_for_detection(capsys, model, photos, tmp_path) -> None:
    big = tmp_path / "big.jpg"
    Image.open(photos["face"]).resize((2600, 2600), Image.Resampling.BILINEAR).save(big, quality=85)
    code, out, err = run(capsys, "encode", big, "-o", tmp_path / "big.npz", "--model", model["onnx"])
    assert code == 0, err
    assert "2600x2600, face" in out


def test_encode_model_errors(capsys, model, photos, tmp_path, monkeypatch) -> None:
    import lp3d.lift.inference

    monkeypatch.setattr(lp3d.lift.inference, "DEFAULT_MODEL", tmp_path / "models" / "small.onnx")
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz")
    assert code == 1 and "--model" in err and "python -m lp3d.train" in err
    lone = tmp_path / "lone.onnx"
    shutil.copy(model["onnx"], lone)
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz", "--model", lone)
    assert code == 1 and "sidecar" in err and "lone.json" in err
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"not a protobuf")
    shutil.copy(model["onnx"].with_suffix(".json"), broken.with_suffix(".json"))
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz", "--model", broken)
    assert code == 1 and "cannot load the ONNX model" in err
    import torch

    odd = tmp_path / "odd.pt"
    torch.save({"weights": torch.zeros(3)}, odd)
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz", "--model", odd)
    assert code == 1 and "layout not understood" in err
    code, _, err = run(
        capsys,
        "encode",
        photos["face"],
        photos["face_crop"],
        "-o",
        tmp_path / "x.npz",
        "--model",
        model["onnx"],
    )
    assert code == 1 and "output folder" in err
    code, _, err = run(
        capsys, "encode", photos["face"], "-o", tmp_path / "no" / "x.npz", "--model", model["onnx"]
    )
    assert code == 1 and "does not exist" in err
    assert not list(tmp_path.glob("*.npz"))


# ============================================================================================== video


@pytest.fixture(scope="module")
def face_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four 160² frames of a slowly panning face."""
    import cv2
    import imageio_ffmpeg
    from skimage.data import astronaut

    path = tmp_path_factory.mktemp("video") / "in.mp4"
    face = astronaut()[:320, 60:380]
    writer = imageio_ffmpeg.write_frames(
        str(path), (160, 160), fps=10, macro_block_size=2, ffmpeg_log_level="error"
    )
    writer.send(None)
    for i in range(4):
        frame = cv2.warpAffine(face, np.float32([[0.5, 0, -2 * i], [0, 0.5, 0]]), (160, 160))
        writer.send(np.ascontiguousarray(frame).tobytes())
    writer.close()
    return path


def test_video_lifts_every_frame(capsys, model, face_video, tmp_path) -> None:
    import imageio_ffmpeg

    out = tmp_path / "out.mp4"
    code, stdout, err = run(
        capsys,
        "video",
        face_video,
        "-o",
        out,
        "--yaw",
        20,
        "--smooth",
        0.5,
        "--model",
        model["onnx"],
        "--side-by-side",
        *SMALL,
    )
    assert code == 0, err
    assert "lifted 4 frames" in stdout and "video" in err  # summary and progress bar
    reader = imageio_ffmpeg.read_frames(str(out))
    assert next(reader)["size"] == (64, 32) and sum(1 for _ in reader) == 4


def test_video_gif_no_detect_and_bad_inputs(capsys, model, face_video, photos, tmp_path) -> None:
    code, _, err = run(
        capsys,
        "video",
        face_video,
        "-o",
        tmp_path / "o.gif",
        "--no-detect",
        "--max-frames",
        2,
        "--model",
        model["onnx"],
        *SMALL,
    )
    assert code == 0, err
    code, _, err = run(
        capsys, "video", photos["text"], "-o", tmp_path / "x.mp4", "--model", model["onnx"], *SMALL
    )
    assert code == 1 and "cannot read as a video" in err
    code, _, err = run(capsys, "video", face_video, "-o", tmp_path / "x.avi", "--model", model["onnx"])
    assert code == 1 and "unsupported format" in err
    code, _, err = run(capsys, "video", face_video, "-o", tmp_path / "x.mp4", "--smooth", 1.0)
    assert code == 2
    for bad in ("-1", "nan", "1e9"):
        code, _, err = run(capsys, "video", face_video, "-o", tmp_path / "x.mp4", "--steady", bad)
        assert code == 2 and "--steady" in err
    assert listing(tmp_path) == {"o.gif"}


def test_video_steady_keeps_every_frame_and_changes_them(capsys, model, face_video, tmp_path) -> None:
    """``--steady`` (issue 21) holds frames back until their window is whole, then flushes: the same
    frames come out, in order, and (σ large against 4 frames) nearer to each other than without it."""
    import imageio_ffmpeg

    outs = {}
    for sigma in ("0", "30"):
        out = tmp_path / f"steady{sigma}.mp4"
        code, stdout, err = run(
            capsys, "video", face_video, "-o", out, "--steady", sigma, "--model", model["onnx"], *SMALL
        )
        assert code == 0, err
        assert "lifted 4 frames" in stdout
        reader = imageio_ffmpeg.read_frames(str(out))
        w, h = next(reader)["size"]
        outs[sigma] = np.stack([np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]).astype(float)
    assert outs["0"].shape == outs["30"].shape and outs["0"].shape[0] == 4
    change = {k: np.abs(np.diff(v, axis=0)).mean() for k, v in outs.items()}
    assert change["30"] < change["0"], change


def test_video_refine_and_flip_average_change_every_frame(capsys, model, face_video, tmp_path) -> None:
    """``lp3d video --refine 1`` (issue 21): each frame's head is fitted to its crop (the camera searched
    for on the first frame, then followed), so the frames differ from plain lifting; so do
    ``--flip-average``'s (each frame encoded with its mirror image)."""
    import imageio_ffmpeg

    frames = {}
    for name, extra in (("plain", ()), ("refined", ("--refine", 1)), ("flipped", ("--flip-average",))):
        out = tmp_path / f"{name}.mp4"
        code, stdout, err = run(
            capsys,
            "video",
            face_video,
            "-o",
            out,
            "--model",
            model["onnx"],
            "--max-frames",
            2,
            "--steady",
            0,
            *SMALL,
            *extra,
        )
        assert code == 0, err
        reader = imageio_ffmpeg.read_frames(str(out))
        w, h = next(reader)["size"]
        frames[name] = np.stack([np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]).astype(float)
    for name in ("refined", "flipped"):
        assert frames["plain"].shape == frames[name].shape and frames["plain"].shape[0] == 2
        assert np.abs(frames["plain"] - frames[name]).mean() > 0.1, name


def test_video_without_faces(capsys, model, tmp_path) -> None:
    import imageio_ffmpeg

    src = tmp_path / "noise.mp4"
    writer = imageio_ffmpeg.write_frames(
        str(src), (64, 64), fps=5, macro_block_size=2, ffmpeg_log_level="error"
    )
    writer.send(None)
    for _ in range(2):
        writer.send(np.full((64, 64, 3), 128, np.uint8).tobytes())
    writer.close()
    code, _, err = run(capsys, "video", src, "-o", tmp_path / "o.mp4", "--model", model["onnx"], *SMALL)
    assert code == 1 and "no face found" in err and "--no-detect" in err
    assert listing(tmp_path) == {"noise.mp4"}


# =============================================================================================== demo


DEMO_SMALL = ("--resolution", 16, "--samples", "4+4", "--frames", 2)


def test_demo_lifts_a_teacher_portrait_and_the_astronaut(capsys, model, tmp_path) -> None:
    out_dir = tmp_path / "demo"
    code, out, err = run(capsys, "demo", "--out", out_dir, "--model", model["onnx"], *DEMO_SMALL)
    assert code == 0, err
    names = ("teacher_portrait", "astronaut")
    expected = {f"{n}{ext}" for n in names for ext in (".npz", ".html", ".crop.png")} | {
        "side_by_side.png",
        "orbit.gif",
    }
    assert listing(out_dir) == expected
    assert (
        "scikit-image astronaut: 512x512, face" in out
    )  # the astronaut's face was detected, not centre-cropped
    for n in names:
        tri = load_triplane(out_dir / f"{n}.npz")
        assert tri.planes.shape == (3, 32, 64, 64) and "lp3d demo" in (tri.source or "")
        assert np.asarray(Image.open(out_dir / f"{n}.crop.png")).shape == (128, 128, 3)
    gif = Image.open(out_dir / "orbit.gif")
    assert gif.n_frames == 2 and gif.size == (2 * 16, 16)  # both heads side by side
    sheet = np.asarray(Image.open(out_dir / "side_by_side.png"))
    assert sheet.shape[0] > 3 * 16  # student rows and the teacher's own views


def test_demo_refine_adds_refined_heads_and_rows(capsys, model, tmp_path) -> None:
    """``lp3d demo --refine 2`` (issue 21): the refined triplanes beside the feed-forward ones, and
    one more row per head in the contact sheet; with ``--flip-average`` the feed-forward heads are
    the flip-averaged ones."""
    plain, refined = tmp_path / "plain", tmp_path / "refined"
    assert run(capsys, "demo", "--out", plain, "--model", model["onnx"], *DEMO_SMALL)[0] == 0
    code, out, err = run(
        capsys,
        "demo",
        "--out",
        refined,
        "--model",
        model["onnx"],
        *DEMO_SMALL,
        "--refine",
        2,
        "--flip-average",
    )
    assert code == 0, err
    assert "teacher_portrait: refined 2 steps" in out and "astronaut: refined 2 steps" in out
    assert {"teacher_portrait.refined.npz", "astronaut.refined.npz"} <= listing(refined)
    a, b = load_triplane(refined / "astronaut.npz"), load_triplane(refined / "astronaut.refined.npz")
    assert "refined 2 steps" in (b.source or "") and not np.array_equal(a.planes, b.planes)
    assert "flip-averaged" in (a.source or "") and "flip-averaged" in out
    assert not np.allclose(a.planes, load_triplane(plain / "astronaut.npz").planes, atol=1e-3)
    rows = {d: np.asarray(Image.open(d / "side_by_side.png")).shape[0] for d in (plain, refined)}
    assert rows[refined] > rows[plain]


def test_demo_with_the_shipped_model(capsys, tmp_path) -> None:
    """``lp3d demo`` as the README runs it (default model), at a small size."""
    code, out, err = run(capsys, "demo", "--out", tmp_path / "demo", *DEMO_SMALL)
    assert code == 0, err
    assert "small.onnx" in out and "config 'small-colour'" in out
    written = listing(tmp_path / "demo")
    assert {"teacher_portrait.npz", "astronaut.npz", "side_by_side.png", "orbit.gif"} <= written
    # The shipped model's 64² head as a web page (lp3d share): within the 3 MB.
    assert (tmp_path / "demo" / "teacher_portrait.html").stat().st_size <= 3_000_000


def test_demo_without_a_model_says_what_to_do(capsys, tmp_path, monkeypatch) -> None:
    import lp3d.lift.inference

    monkeypatch.setattr(lp3d.lift.inference, "DEFAULT_MODEL", tmp_path / "models" / "small.onnx")
    code, _, err = run(capsys, "demo", "--out", tmp_path / "demo", *DEMO_SMALL)
    assert code == 1 and "--model" in err and "python -m lp3d.train" in err
    assert not (tmp_path / "demo").exists()


# ============================================================================== model package, photo


def test_model_package_round_trip_and_errors(model, tmp_path) -> None:
    pkg = load_model_package(model["onnx"])
    assert load_model_package(model["onnx"].with_suffix(".json")).model_path == model["onnx"]
    assert pkg.image_size == 128 and pkg.triplane_resolution == 64 and pkg.config_name == "tiny"
    tri = coloured_sphere(size=8)
    np.testing.assert_array_equal(pkg.w0, tri.w0)  # JSON round trip is exact
    np.testing.assert_array_equal(pkg.b1, tri.b1)
    data = json.loads(model["onnx"].with_suffix(".json").read_text())
    side = tmp_path / "m.json"
    for change, words in (
        ({"format": "other"}, "not an lp3d model package"),
        ({"format_version": 99}, "format_version 99"),
        ({"decoder": {**data["decoder"], "w0": [[0.0] * 32] * 63}}, "decoder.w0: shape"),
        ({"ray_end": 1.0}, "ray_end"),
        ({"image_size": "big"}, "image_size"),
    ):
        side.write_text(json.dumps({**data, **change}))
        with pytest.raises(ModelPackageError, match=words.replace("(", r"\(")):
            load_model_package(side)
    side.write_text("{ not json")
    with pytest.raises(ModelPackageError, match="unreadable"):
        load_model_package(side)
    with pytest.raises(ModelPackageError, match="shape"):
        save_model_package(tmp_path / "x.onnx", (tri.w0[:5], tri.b0, tri.w1, tri.b1), "tiny", (1, 2, 3))


def test_load_image_modes(tmp_path) -> None:
    from lp3d.photo import load_image

    deep = tmp_path / "deep.png"
    Image.fromarray(np.full((20, 20), 65535, np.uint16)).save(deep)
    rgb, notes = load_image(deep)
    assert rgb.shape == (20, 20, 3) and rgb.max() == 255 and any("grayscale" in n for n in notes)
    pal = tmp_path / "pal.png"
    Image.new("P", (20, 20), 3).save(pal, transparency=0)
    rgb, notes = load_image(pal)
    assert rgb.shape == (20, 20, 3) and any("alpha" in n for n in notes)
    cmyk = tmp_path / "cmyk.jpg"
    Image.new("CMYK", (20, 20), (0, 255, 255, 0)).save(cmyk)
    rgb, notes = load_image(cmyk)
    assert rgb.shape == (20, 20, 3) and rgb[10, 10, 0] > 200 and any("CMYK" in n for n in notes)
    tiny = tmp_path / "tiny.png"
    Image.new("RGB", (8, 8)).save(tiny)
    with pytest.raises(ValueError, match="too small"):
        load_image(tiny)


def test_alignment_levels_a_tilted_face(photos) -> None:
    import cv2

    from lp3d.photo import Crop, detect_face

    face = np.asarray(Image.open(photos["face"]))
    base = detect_face(face)
    assert base is not None
    # Turn the photo 8° counter-clockwise on screen: the face's roll drops by 8°.
    turned = cv2.warpAffine(face, cv2.getRotationMatrix2D((224.0, 113.0), 8.0, 1.0), (512, 512))
    found = detect_face(turned)
    assert found is not None
    assert abs((base.alignment.roll_deg - found.alignment.roll_deg) - 8.0) < 1.5
    # The crop centre maps to the output centre.
    crop = Crop(cx=100.0, cy=50.0, side=40.0, angle_deg=30.0)
    m = crop.matrix(64)
    np.testing.assert_allclose(m @ [100.0, 50.0, 1.0], [31.5, 31.5], atol=1e-9)


def test_video_helpers() -> None:
    from lp3d.photo import Crop
    from lp3d.photo.video import nearest_hits, smooth_crops

    np.testing.assert_array_equal(nearest_hits(np.array([2, 5, 9]), 11), [2, 2, 2, 2, 5, 5, 5, 5, 9, 9, 9])
    crops = [Crop(10.0, 10.0, 50.0), Crop(20.0, 10.0, 50.0), Crop(10.0, 10.0, 50.0)]
    smooth = smooth_crops(crops, 0.5)
    assert 10.0 < smooth[0].cx < smooth[1].cx < 20.0 and smooth[1].side == 50.0
