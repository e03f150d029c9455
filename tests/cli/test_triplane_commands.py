"""``lp3d render``, ``orbit``, ``mesh`` and ``info``: the commands that take a triplane file, with
their bad inputs (a clear one-line error, a non-zero exit status, no output left behind).

Renders are tiny (32², 12+12 samples)."""

from __future__ import annotations

import json
import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.render.triplane_io import load_triplane
from support.cli import SMALL, SPHERE_RADIUS, listing, run


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
