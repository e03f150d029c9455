"""Mesh files written by ``lp3d.render.mesh`` (trimesh) and read back: every format gives the positions,
normals, faces and colours of the Mesh written.

Tolerances: binary PLY and GLB store float32, so positions come back exactly, and so do binary PLY's
normals (GLB's within 1e-6: trimesh re-normalises them); ASCII PLY and OBJ print 8 decimals, so
positions and normals come back within 1e-8. Colours: PLY and OBJ hold 8-bit colours, which
come back exactly (``round(255 c)``); GLB's COLOR_0 is float32 linear (glTF vertex colours are linear)
and comes back within 1e-6 of the sRGB transfer function applied to the Mesh's colours in float64.
The files are parsed here by hand from the format specifications, and once more with ``trimesh.load``.
"""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from lp3d.render.mesh import Mesh, extract_mesh, write_glb, write_mesh, write_obj, write_ply
from lp3d.render.sample_scenes import coloured_sphere


@pytest.fixture(scope="module")
def mesh() -> Mesh:
    """A marching-cubes sphere with colours over all of [0, 1], dark sRGB values and the ends included."""
    m = extract_mesh(coloured_sphere(size=32, radius=0.3), grid=24)
    colors = np.random.default_rng(0).uniform(0.0, 1.0, m.colors.shape).astype(np.float32)
    colors[:6] = np.array([0.0, 1.0, 0.5 / 255, 0.02, 0.04045, 0.9999], np.float32)[:, None]
    return dataclasses.replace(m, colors=colors)


def _uint8(colors: np.ndarray) -> np.ndarray:
    """8-bit colours as the hand-written writers made them: round(255 c) in float32."""
    return np.round(np.asarray(colors, np.float32) * np.float32(255)).astype(np.uint8)


def _srgb_to_linear64(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# ------------------------------------------------------------------------------------------ readers

_PLY_TYPES = {"float": "f4", "uchar": "u1", "int": "i4", "uint": "u4", "double": "f8"}


def _read_ply(path: Path) -> tuple[str, dict[str, np.ndarray], np.ndarray]:
    """(format, vertex fields by name, faces (F, 3)) for PLY with one vertex and one triangle element."""
    data = path.read_bytes()
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode("ascii").splitlines()
    assert lines[0] == "ply"
    fmt = next(ln.split()[1] for ln in lines if ln.startswith("format "))
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for ln in lines:
        words = ln.split()
        if words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            elements[-1][2].append((words[-1], " ".join(words[1:-1])))
    (vname, n_vert, vprops), (fname, n_face, fprops) = elements
    assert (vname, fname) == ("vertex", "face")
    assert fprops == [("vertex_indices", "list uchar int")]
    if fmt == "binary_little_endian":
        vdt = np.dtype([(name, "<" + _PLY_TYPES[t]) for name, t in vprops])
        verts = np.frombuffer(body, vdt, n_vert)
        fdt = np.dtype([("k", "u1"), ("i", "<i4", 3)])
        face_rec = np.frombuffer(body, fdt, n_face, offset=vdt.itemsize * n_vert)
        assert len(body) == vdt.itemsize * n_vert + fdt.itemsize * n_face
        assert (face_rec["k"] == 3).all()
        return fmt, {name: verts[name] for name in vdt.names}, face_rec["i"].astype(np.int64)
    assert fmt == "ascii"
    rows = body.decode("ascii").split("\n")
    assert rows[-1] == "" and all(rows[:-1])  # one row per vertex and face, newline-terminated
    table = np.array([r.split() for r in rows[:n_vert]], dtype=np.float64)
    faces = np.array([r.split() for r in rows[n_vert:-1]], dtype=np.int64)
    assert len(faces) == n_face and (faces[:, 0] == 3).all()
    return fmt, {name: table[:, i] for i, (name, _) in enumerate(vprops)}, faces[:, 1:]


def _read_obj(path: Path) -> dict[str, np.ndarray]:
    rows: dict[str, list[list[str]]] = {"v": [], "vn": [], "f": []}
    for line in path.read_text(encoding="ascii").splitlines():
        words = line.split()
        if words and words[0] in rows:
            rows[words[0]].append(words[1:])
        else:
            assert not words or words[0] == "#", line  # nothing else: no material, no texture
    faces = [[corner.split("//") for corner in face] for face in rows["f"]]
    return {
        "v": np.array(rows["v"], np.float64),
        "vn": np.array(rows["vn"], np.float64),
        "f": np.array(faces, np.int64),  # (F, 3, 2): vertex and normal index per corner, 1-based
    }


_COMPONENTS = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "u1"}
_WIDTHS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


def _read_glb(path: Path) -> tuple[dict, dict[str, np.ndarray], np.ndarray]:
    """(glTF JSON, attribute arrays by name, faces (F, 3)) of a one-primitive GLB."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    doc = json.loads(data[20 : 20 + json_len])
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_type == 0x004E4942 and 28 + json_len + bin_len == len(data)
    binary = data[28 + json_len :]
    assert doc["buffers"][0]["byteLength"] <= bin_len  # the chunk may be padded

    def accessor(i: int) -> np.ndarray:
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        assert "byteStride" not in view
        dtype, width = np.dtype(_COMPONENTS[acc["componentType"]]), _WIDTHS[acc["type"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        assert start % dtype.itemsize == 0
        assert acc.get("byteOffset", 0) + acc["count"] * width * dtype.itemsize <= view["byteLength"]
        arr = np.frombuffer(binary, dtype, acc["count"] * width, start).reshape(acc["count"], width)
        if acc.get("normalized"):
            return arr / np.float64(np.iinfo(dtype).max)
        return arr

    (gltf_mesh,) = doc["meshes"]
    (prim,) = gltf_mesh["primitives"]
    assert prim.get("mode", 4) == 4  # triangles
    attrs = {name: accessor(i) for name, i in prim["attributes"].items()}
    return doc, attrs, accessor(prim["indices"]).reshape(-1, 3)


# -------------------------------------------------------------------------------------------- tests


@pytest.mark.parametrize("binary", [True, False])
def test_ply_reads_back(mesh, tmp_path, binary) -> None:
    path = tmp_path / "m.ply"
    write_ply(path, mesh, binary=binary)
    fmt, v, faces = _read_ply(path)
    assert fmt == ("binary_little_endian" if binary else "ascii")
    assert list(v) == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"]
    pos = np.stack([v["x"], v["y"], v["z"]], axis=1)
    normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1)
    rgba = np.stack([v["red"], v["green"], v["blue"], v["alpha"]], axis=1)
    if binary:
        assert pos.dtype == np.float32 and rgba.dtype == np.uint8
        np.testing.assert_array_equal(pos, mesh.vertices)
        np.testing.assert_array_equal(normals, mesh.normals)
    else:
        np.testing.assert_allclose(pos, mesh.vertices, rtol=0, atol=1e-8)
        np.testing.assert_allclose(normals, mesh.normals, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(faces, mesh.faces)
    np.testing.assert_array_equal(rgba[:, :3], _uint8(mesh.colors))
    assert (rgba[:, 3] == 255).all()


def test_obj_reads_back(mesh, tmp_path) -> None:
    path = tmp_path / "m.obj"
    write_obj(path, mesh)
    obj = _read_obj(path)
    assert obj["v"].shape == (len(mesh.vertices), 6)  # x y z r g b
    np.testing.assert_allclose(obj["v"][:, :3], mesh.vertices, rtol=0, atol=1e-8)
    np.testing.assert_allclose(obj["vn"], mesh.normals, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(obj["f"][:, :, 0] - 1, mesh.faces)
    np.testing.assert_array_equal(obj["f"][:, :, 1], obj["f"][:, :, 0])  # normal i belongs to vertex i
    assert obj["v"][:, 3:].min() >= 0.0 and obj["v"][:, 3:].max() <= 1.0
    np.testing.assert_array_equal(_uint8(obj["v"][:, 3:]), _uint8(mesh.colors))
    assert [p.name for p in tmp_path.iterdir()] == ["m.obj"]  # no material file beside it


def test_glb_reads_back(mesh, tmp_path) -> None:
    path = tmp_path / "m.glb"
    write_glb(path, mesh)
    doc, attrs, faces = _read_glb(path)
    assert doc["asset"]["version"] == "2.0"
    assert set(attrs) == {"POSITION", "NORMAL", "COLOR_0"}
    np.testing.assert_array_equal(attrs["POSITION"], mesh.vertices)
    np.testing.assert_allclose(attrs["NORMAL"], mesh.normals, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(faces, mesh.faces)
    position = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    np.testing.assert_array_equal(position["min"], mesh.vertices.min(axis=0))  # required by glTF
    np.testing.assert_array_equal(position["max"], mesh.vertices.max(axis=0))
    # COLOR_0 is float, linear, 3 channels: no 8-bit rounding after the transfer function (which
    # would turn sRGB levels 0..6 of 255 black and show colours up to 6 levels off).
    color = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]]
    assert (color["componentType"], color["type"]) == (5126, "VEC3")
    np.testing.assert_allclose(attrs["COLOR_0"], _srgb_to_linear64(mesh.colors), rtol=0, atol=1e-6)
    assert 0 < attrs["COLOR_0"][2, 0] < 1 / 255 and attrs["COLOR_0"][3, 0] < attrs["COLOR_0"][4, 0]


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_trimesh_loads_what_we_write(mesh, tmp_path, suffix) -> None:
    import trimesh

    path = tmp_path / f"m{suffix}"
    write_mesh(path, mesh)
    # Not force="mesh": that concatenates the scene and drops the normals read from the file.
    loaded = trimesh.load(path, process=False, maintain_order=True)
    if isinstance(loaded, trimesh.Scene):  # GLB
        (loaded,) = loaded.geometry.values()
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    np.testing.assert_allclose(loaded.vertex_normals, mesh.normals, rtol=0, atol=1e-6)
    rgb = loaded.visual.vertex_colors[:, :3]
    if suffix == ".glb":  # trimesh turns the float linear colours into 8 bits
        np.testing.assert_allclose(rgb, _srgb_to_linear64(mesh.colors) * 255, atol=0.5 + 1e-6)
    else:
        np.testing.assert_array_equal(rgb, _uint8(mesh.colors))


def test_write_mesh_formats(mesh, tmp_path) -> None:
    write_mesh(tmp_path / "a.bin", mesh, fmt=".PLY", ascii_ply=True)
    assert _read_ply(tmp_path / "a.bin")[0] == "ascii"
    write_mesh(tmp_path / "b.GLB", mesh)
    assert (tmp_path / "b.GLB").read_bytes()[:4] == b"glTF"
    with pytest.raises(ValueError, match="unsupported mesh format '.stl'"):
        write_mesh(tmp_path / "c.stl", mesh)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.GLB"]
