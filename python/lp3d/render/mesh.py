"""Triplane to mesh: a density grid, marching cubes, vertex colours, and PLY / OBJ / GLB files (trimesh).

The grid samples the decoder's raw density ``sigma_raw`` (EG3D's ``out[0]``, before the marcher's
softplus) at ``grid``³ points spanning the triplane box ``[-box_warp/2, box_warp/2]³``, with the
reference's semantics (:func:`~lp3d.render.reference.grid_sample_bilinear`,
:func:`~lp3d.render.reference.decode`).
Because each plane depends on two axes only, the three planes are sampled on ``grid``² points each and
broadcast-added, so only the decoder runs per grid point (float32, in slabs). The surface is
``skimage.measure.marching_cubes`` at ``threshold`` (EG3D's shape extraction uses level 10); a border
of empty voxels closes it at the box faces. Vertex colours are the decoder's RGB features
(sigmoid outputs 1..3, in [0, 1]) at the vertices.

World axes are kept (y up, the face looks toward +z), which is glTF's convention too. trimesh writes the
files (layouts in the writers' docstrings) to the path given; ``lp3d mesh`` gives a temporary file from
:mod:`lp3d.atomic` and publishes it once written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lp3d.render.reference import decode, grid_sample_bilinear, sample_triplane
from lp3d.render.triplane import PLANE_AXES, TriplaneData

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "EG3D_MESH_THRESHOLD",
    "Mesh",
    "MeshError",
    "density_grid",
    "extract_mesh",
    "glb_bytes",
    "ply_bytes",
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
        # Overflow (planes or weights too large for float32) is reported by extract_mesh, by name.
        with np.errstate(over="ignore", invalid="ignore"):
            h = _softplus(feats.reshape(-1, feats.shape[-1]) @ w0t + b0)
            out[sl] = (h @ w1s + b1s).reshape(sl.stop - i, grid, grid)  # density only: 1 of 33 outputs
    return out


def extract_mesh(tri: TriplaneData, *, grid: int = 128, threshold: float = EG3D_MESH_THRESHOLD) -> Mesh:
    """Marching cubes on :func:`density_grid` at ``threshold``, with decoder colours at the vertices.

    Raises :class:`MeshError` when the density never crosses ``threshold`` inside the box.
    """
    from skimage.measure import marching_cubes

    sigma = density_grid(tri, grid)
    bad = int(np.count_nonzero(~np.isfinite(sigma)))
    if bad:
        raise MeshError(
            f"the decoder's density is not finite (NaN or Inf in float32) at {bad} of the {sigma.size} grid "
            "points: the planes or the decoder weights are too large for float32"
        )
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
        with np.errstate(over="ignore"):  # a saturated sigmoid is 0 or 1, as it should be
            feats = sample_triplane(tri.planes, points[i : i + chunk], box_warp=tri.box_warp)
            _, rgb = decode(feats, tri.w0, tri.b0, tri.w1, tri.b1)
        out[i : i + chunk] = np.clip(rgb[:, :3], 0.0, 1.0)
    return out


# ------------------------------------------------------------------------------------------ writers


def _colors_uint8(colors: np.ndarray) -> np.ndarray:
    return np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)


def _trimesh(mesh: Mesh, *, colors: bool = True, **extra: object) -> trimesh.Trimesh:
    """``mesh`` as a :class:`trimesh.Trimesh` kept exactly as given: no vertex merging or reordering
    (``process=False``), our normals (not recomputed) and, with ``colors``, 8-bit vertex colours."""
    import trimesh

    return trimesh.Trimesh(
        vertices=mesh.vertices,
        faces=mesh.faces,
        vertex_normals=mesh.normals,
        vertex_colors=_colors_uint8(mesh.colors) if colors else None,
        process=False,
        validate=False,
        **extra,
    )


def _write(path: str | os.PathLike[str], data: bytes | str) -> None:
    # ``path`` is the caller's temporary file (lp3d.atomic), published by the caller.
    with open(path, "wb") as out:
        out.write(data.encode("ascii") if isinstance(data, str) else data)


def ply_bytes(mesh: Mesh, *, binary: bool = True) -> bytes:
    """PLY (trimesh): float x y z, nx ny nz, uchar red green blue alpha (255) per vertex and
    uchar-counted int faces; binary little-endian or ASCII."""
    encoding = "binary" if binary else "ascii"
    data = _trimesh(mesh).export(
        file_type="ply", encoding=encoding, vertex_normal=True, include_attributes=False
    )
    return data.encode("ascii") if isinstance(data, str) else data


def write_ply(path: str | os.PathLike[str], mesh: Mesh, *, binary: bool = True) -> None:
    """:func:`ply_bytes` into ``path``."""
    _write(path, ply_bytes(mesh, binary=binary))


def write_obj(path: str | os.PathLike[str], mesh: Mesh) -> None:
    """Wavefront OBJ (trimesh): ``v x y z r g b`` (8-bit colours as fractions in [0, 1], read by
    MeshLab/Blender), ``vn`` normals and 1-based ``f a//a b//b c//c`` faces; no material file."""
    text = _trimesh(mesh).export(
        file_type="obj", include_normals=True, include_color=True, include_texture=False
    )
    _write(path, text)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _color_0(tree: dict) -> None:
    """trimesh writes custom vertex attributes with a leading underscore; glTF's own is ``COLOR_0``."""
    for gltf_mesh in tree["meshes"]:
        for prim in gltf_mesh["primitives"]:
            attrs = prim["attributes"]
            key = next((k for k in ("_COLOR_0", "COLOR_0") if k in attrs), None)
            if key is None:
                raise RuntimeError(f"trimesh wrote no COLOR_0 attribute (got {sorted(attrs)})")
            attrs["COLOR_0"] = attrs.pop(key)


def glb_bytes(mesh: Mesh) -> bytes:
    """glTF 2.0 binary (trimesh): one mesh, one triangle primitive with POSITION, NORMAL, COLOR_0 and
    uint32 indices. COLOR_0 is float VEC3 and linear (glTF vertex colours are linear, so the decoder's
    sRGB colours are converted). Float rather than trimesh's 8-bit colours: 8-bit linear keeps 183 of
    the 256 sRGB levels, shows the darkest 7 as black and others up to 6 levels off. trimesh writes it
    as a custom attribute and :func:`_color_0` names it ``COLOR_0``."""
    tm = _trimesh(mesh, colors=False, vertex_attributes={"COLOR_0": _srgb_to_linear(mesh.colors)})
    return tm.export(file_type="glb", include_normals=True, tree_postprocessor=_color_0)


def write_glb(path: str | os.PathLike[str], mesh: Mesh) -> None:
    """:func:`glb_bytes` into ``path``."""
    _write(path, glb_bytes(mesh))


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
