"""Triplane to mesh: a density grid, marching cubes, vertex colours, and PLY / OBJ / GLB writers.

The grid samples the decoder's raw density ``sigma_raw`` (EG3D's ``out[0]``, before the marcher's
softplus) at ``grid``³ points spanning the triplane box ``[-box_warp/2, box_warp/2]³``, with the
reference's semantics (:func:`~lp3d.render.reference.grid_sample_bilinear`,
:func:`~lp3d.render.reference.decode`).
Because each plane depends on two axes only, the three planes are sampled on ``grid``² points each and
broadcast-added, so only the decoder runs per grid point (float32, in slabs). The surface is
``skimage.measure.marching_cubes`` at ``threshold`` (EG3D's shape extraction uses level 10); a border
of empty voxels closes it at the box faces. Vertex colours are the decoder's RGB features
(sigmoid outputs 1..3, in [0, 1]) at the vertices.

World axes are kept (y up, the face looks toward +z), which is glTF's convention too.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lp3d.render.reference import decode, grid_sample_bilinear, sample_triplane
from lp3d.render.triplane import PLANE_AXES, TriplaneData

__all__ = [
    "EG3D_MESH_THRESHOLD",
    "Mesh",
    "MeshError",
    "density_grid",
    "extract_mesh",
    "write_glb",
    "write_obj",
    "write_ply",
]

#: EG3D's gen_samples.py extracts shapes at raw density 10.
EG3D_MESH_THRESHOLD = 10.0
#: Grid points per decoder slab: bounds the (points, 64) float32 temporaries to ~30 MB.
_SLAB_POINTS = 1 << 17


class MeshError(ValueError):
    """No surface can be extracted (e.g. the threshold is outside the density range)."""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh: ``vertices`` (V, 3) float32 world units, ``faces`` (F, 3) uint32 (counter-clockwise
    seen from outside), ``normals`` (V, 3) float32 unit outward, ``colors`` (V, 3) float32 in [0, 1]
    (the decoder's colours, display/sRGB values)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    colors: np.ndarray


def _softplus(x: np.ndarray) -> np.ndarray:
    # torch's Softplus (threshold 20), in float32.
    return np.where(x > 20.0, x, np.log1p(np.exp(np.minimum(x, 20.0))))


def density_grid(tri: TriplaneData, grid: int) -> np.ndarray:
    """Raw density (grid, grid, grid) float32 indexed ``[ix, iy, iz]`` at ``linspace(-b/2, b/2, grid)``
    on each axis (``b = box_warp``)."""
    if grid < 2:
        raise ValueError(f"grid must be >= 2, got {grid}")
    half = tri.box_warp / 2.0
    q = np.linspace(-half, half, grid) * (2.0 / tri.box_warp)  # normalised coordinates in [-1, 1]
    U, V = np.meshgrid(q, q, indexing="ij")
    planes = tri.planes.astype(np.float32)
    terms: list[np.ndarray] = []
    for p, (a, b) in enumerate(PLANE_AXES):
        s = grid_sample_bilinear(planes[p], U, V).astype(np.float32)  # (grid, grid, C) over axes (a, b)
        if a > b:
            s = s.transpose(1, 0, 2)  # order the two world axes ascending
        missing = ({0, 1, 2} - {a, b}).pop()
        terms.append(np.expand_dims(s, missing))  # broadcastable over (x, y, z, C)
    w0t, b0 = tri.w0.T.astype(np.float32), tri.b0.astype(np.float32)
    w1s, b1s = tri.w1[0].astype(np.float32), np.float32(tri.b1[0])
    out = np.empty((grid, grid, grid), np.float32)
    step = max(1, _SLAB_POINTS // (grid * grid))
    for i in range(0, grid, step):
        sl = slice(i, min(grid, i + step))
        feats = sum(
            np.broadcast_to(t[sl] if t.shape[0] > 1 else t, (sl.stop - i, grid, grid, t.shape[-1]))
            for t in terms
        ) / np.float32(len(PLANE_AXES))
        h = _softplus(feats.reshape(-1, feats.shape[-1]) @ w0t + b0)
        out[sl] = (h @ w1s + b1s).reshape(sl.stop - i, grid, grid)  # density only: 1 of 33 outputs
    return out


def extract_mesh(tri: TriplaneData, *, grid: int = 128, threshold: float = EG3D_MESH_THRESHOLD) -> Mesh:
    """Marching cubes on :func:`density_grid` at ``threshold``, with decoder colours at the vertices.

    Raises :class:`MeshError` when the density never crosses ``threshold`` inside the box.
    """
    from skimage.measure import marching_cubes

    sigma = density_grid(tri, grid)
    lo, hi = float(sigma.min()), float(sigma.max())
    if not lo < threshold < hi:
        raise MeshError(
            f"no surface at threshold {threshold:g}: the density inside the box ranges over "
            f"[{lo:.3g}, {hi:.3g}]; pick a --threshold inside it"
        )
    # A border of empty voxels closes the surface where it meets the box faces.
    padded = np.pad(sigma, 1, mode="constant", constant_values=min(lo, threshold) - 1.0)
    step = tri.box_warp / (grid - 1)
    verts, faces, normals, _ = marching_cubes(padded, level=threshold, spacing=(step, step, step))
    half = tri.box_warp / 2.0
    verts = np.clip(verts - step - half, -half, half).astype(np.float32)  # undo the padding offset
    # skimage's default (gradient "descent") treats larger values as inside: normals point outward.
    # Its faces wind clockwise seen from outside in these (x, y, z) axes, so flip them for glTF/PLY.
    faces = np.ascontiguousarray(faces[:, ::-1], dtype=np.uint32)
    normals = normals.astype(np.float32)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    colors = vertex_colors(tri, verts)
    return Mesh(vertices=verts, faces=faces, normals=normals, colors=colors)


def vertex_colors(tri: TriplaneData, points: np.ndarray, chunk: int = 1 << 15) -> np.ndarray:
    """The decoder's RGB (features 0..2 after sigmoid, in [0, 1]) at points (V, 3) -> (V, 3) float32."""
    out = np.empty((len(points), 3), np.float32)
    for i in range(0, len(points), chunk):
        feats = sample_triplane(tri.planes, points[i : i + chunk], box_warp=tri.box_warp)
        _, rgb = decode(feats, tri.w0, tri.b0, tri.w1, tri.b1)
        out[i : i + chunk] = np.clip(rgb[:, :3], 0.0, 1.0)
    return out


# ------------------------------------------------------------------------------------------ writers


def _colors_uint8(colors: np.ndarray) -> np.ndarray:
    return np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_ply(path: str | os.PathLike[str], mesh: Mesh, *, binary: bool = True) -> None:
    """PLY with float x y z, nx ny nz, uchar red green blue per vertex and uchar-counted int faces."""
    v, f = mesh.vertices, mesh.faces
    header = (
        "ply\n"
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        "comment written by lp3d mesh\n"
        f"element vertex {len(v)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(f)}\n"
        "property list uchar int vertex_indices\n"
        "end_header\n"
    )
    rgb = _colors_uint8(mesh.colors)
    with open(path, "wb") as out:
        out.write(header.encode("ascii"))
        if binary:
            vdt = np.dtype([("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)])
            va = np.empty(len(v), vdt)
            va["p"], va["n"], va["c"] = v, mesh.normals, rgb
            out.write(va.tobytes())
            fdt = np.dtype([("k", "u1"), ("i", "<i4", 3)])
            fa = np.empty(len(f), fdt)
            fa["k"], fa["i"] = 3, f.astype(np.int32)
            out.write(fa.tobytes())
        else:
            lines = [
                f"{p[0]:.6g} {p[1]:.6g} {p[2]:.6g} {n[0]:.5g} {n[1]:.5g} {n[2]:.5g} {c[0]} {c[1]} {c[2]}\n"
                for p, n, c in zip(v.tolist(), mesh.normals.tolist(), rgb.tolist(), strict=True)
            ]
            lines += [f"3 {a} {b} {c}\n" for a, b, c in f.tolist()]
            out.write("".join(lines).encode("ascii"))


def write_obj(path: str | os.PathLike[str], mesh: Mesh) -> None:
    """Wavefront OBJ: ``v x y z r g b`` (colours in [0, 1] as extra columns, read by MeshLab/Blender),
    ``vn`` normals and 1-based ``f a//a b//b c//c`` faces."""
    v, n, c = mesh.vertices.tolist(), mesh.normals.tolist(), np.clip(mesh.colors, 0, 1).tolist()
    parts = ["# written by lp3d mesh\n"]
    parts += [
        f"v {p[0]:.6g} {p[1]:.6g} {p[2]:.6g} {q[0]:.4f} {q[1]:.4f} {q[2]:.4f}\n"
        for p, q in zip(v, c, strict=True)
    ]
    parts += [f"vn {p[0]:.5g} {p[1]:.5g} {p[2]:.5g}\n" for p in n]
    parts += [f"f {a}//{a} {b}//{b} {d}//{d}\n" for a, b, d in (mesh.faces.astype(np.int64) + 1).tolist()]
    with open(path, "w", encoding="ascii") as out:
        out.write("".join(parts))


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


#: glTF constants.
_FLOAT, _UINT32 = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _CHUNK_JSON, _CHUNK_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


def write_glb(path: str | os.PathLike[str], mesh: Mesh) -> None:
    """A minimal glTF 2.0 binary: one mesh, one triangle primitive with POSITION, NORMAL, COLOR_0
    (float VEC3, linear: glTF vertex colours are linear, so the decoder's sRGB colours are converted)
    and uint32 indices, in one buffer."""
    blobs = [
        np.ascontiguousarray(mesh.vertices, "<f4"),
        np.ascontiguousarray(mesh.normals, "<f4"),
        np.ascontiguousarray(_srgb_to_linear(mesh.colors), "<f4"),
        np.ascontiguousarray(mesh.faces, "<u4"),
    ]
    views, offset = [], 0
    for i, blob in enumerate(blobs):
        views.append(
            {
                "buffer": 0,
                "byteOffset": offset,
                "byteLength": blob.nbytes,
                "target": _ELEMENT_ARRAY_BUFFER if i == 3 else _ARRAY_BUFFER,
            }
        )
        offset += blob.nbytes  # every blob is a multiple of 4 bytes: offsets stay aligned
    n = len(mesh.vertices)
    accessors = [
        {
            "bufferView": 0,
            "componentType": _FLOAT,
            "count": n,
            "type": "VEC3",
            "min": mesh.vertices.min(axis=0).astype(float).tolist(),
            "max": mesh.vertices.max(axis=0).astype(float).tolist(),
        },
        {"bufferView": 1, "componentType": _FLOAT, "count": n, "type": "VEC3"},
        {"bufferView": 2, "componentType": _FLOAT, "count": n, "type": "VEC3"},
        {"bufferView": 3, "componentType": _UINT32, "count": int(mesh.faces.size), "type": "SCALAR"},
    ]
    doc = {
        "asset": {"version": "2.0", "generator": "lp3d mesh"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "lp3d"}],
        "meshes": [
            {
                "primitives": [
                    {"attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2}, "indices": 3, "mode": 4}
                ]
            }
        ],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)  # chunks are 4-byte aligned; JSON pads with spaces
    binary = b"".join(b.tobytes() for b in blobs)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    with open(path, "wb") as out:
        out.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        out.write(struct.pack("<II", len(js), _CHUNK_JSON))
        out.write(js)
        out.write(struct.pack("<II", len(binary), _CHUNK_BIN))
        out.write(binary)


#: Writers by suffix.
WRITERS = {".ply": write_ply, ".obj": write_obj, ".glb": write_glb}


def write_mesh(path: Path, mesh: Mesh, *, fmt: str | None = None, ascii_ply: bool = False) -> None:
    """Write ``mesh`` in the format of ``fmt`` (a suffix such as ``.glb``) or of ``path``'s suffix."""
    suffix = (fmt or path.suffix).lower()
    if suffix == ".ply":
        write_ply(path, mesh, binary=not ascii_ply)
    elif suffix in WRITERS:
        WRITERS[suffix](path, mesh)
    else:
        raise ValueError(f"unsupported mesh format {suffix!r} (use .ply, .obj or .glb)")
