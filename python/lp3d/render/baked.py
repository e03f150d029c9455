"""The baked field's float64 reference (``docs/baked.md``): what ``shaders/bake.wgsl`` stores and what
``shaders/baked.wgsl`` looks up, stated as slow, obvious NumPy, for the tests of the GPU's
``lp3d_render.bake`` and ``render(..., baked_subdivisions=k)``.

A baked field is the occupancy grid's G³ cells, each split into k³ sub-cells; a cell that holds a
*brick* stores its (k + 1)³ corner points, each (sigma_raw, w r, w g, w b) as float16: the raw density
and the RGB premultiplied by the point's colour weight ``w`` (:func:`colour_weight`, computed from the
stored float16 raw density). ``index`` (G, G, G) gives each cell's brick number or -1; ``values``
(bricks, k+1, k+1, k+1, 4) the points. Point (a, b, c) of the brick of cell (ix, iy, iz) sits at plane
coordinates ``-1 + 2 ((ix, iy, iz) k + (a, b, c)) / (G k)``. A point in a cell without a brick has raw
density :data:`EMPTY_RAW` and RGB 0.

A *two-level* field (``fine_subdivisions`` k_f > k) splits the bricks a surface crosses, or a colour
edge under one (:func:`needs_fine`, judged on their k-point values) into k_f³ sub-cells: ``index``
numbers the coarse bricks 0..N_c in cell order, then the fine ones N_c.. in cell order; ``values``
holds the N_c coarse bricks and ``fine_values`` (fine bricks, k_f+1, k_f+1, k_f+1, 4) the others
(:func:`split_levels`).

Why premultiplied: at a surface, half of a sample's corners may lie in empty space, where the
decoder's colour is anything; weighting each corner's colour by a weight that grows with its density
keeps it out of the surface's colour (measured against exact 192+192 by ``bench/baked_error.py``;
``bench/history/RESULTS.md``, "Premultiplied colour").
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.atomic import atomic_path
from lp3d.render import npz_reader
from lp3d.render.reference import decode, render_with, sample_triplane
from lp3d.render.settings import RenderSettings
from lp3d.render.triplane import TriplaneData

#: The raw density of a point in a cell without a brick (``BAKED_EMPTY_RAW`` in ``baked.wgsl``).
EMPTY_RAW = -60.0
#: Every point's colour weight is at least this (``BAKED_COLOUR_FLOOR``). Where all eight corners are
#: nearly transparent the colour is their plain mean, not a ratio of float16 roundings. And it bounds
#: how fast the colour turns within a sub-cell next to a surface: EG3D's compositing gives an interval
#: the mean colour of its two samples, so a transparent sample beside an opaque one is seen, and its
#: colour must not hang on float32's rounding of its position (with 1e-3, one ray of the tests moved
#: by 3e-4). Measured against exact mode (``bench/baked_error.py``), a floor this small costs next to
#: nothing, where a larger one (0.1) costs visibly.
COLOUR_FLOOR = 0.03
#: Above the floor the weight climbs linearly with the raw density, from 0 to 1 at this raw density
#: (``BAKED_COLOUR_RAMP``; about 0.6 opacity over a 48-sample step). A ramp rather than the opacity
#: itself: no exp or log for each of a sample's eight corners (a noticeable share of a baked frame),
#: and as accurate (``bench/baked_error.py``), at this ramp or others.
COLOUR_RAMP = 50.0


#: A brick is crossed by a surface when a point's raw density is above this and another's below
#: :data:`CROSSED_SOLID` (Rust's ``baked::CROSSED_DENSE`` / ``CROSSED_SOLID``).
CROSSED_DENSE = 10.0
CROSSED_SOLID = 50.0
#: A brick whose raw density stays above ``CROSSED_SOLID`` but falls below this lies in the shell
#: just under a surface, still seen through it; it is made fine too when its dense points' colour
#: spans more than ``FINE_COLOUR_STEP`` in a channel of the decoder's [0, 1] RGB (an eyebrow's or a
#: lip's edge, which k points per cell edge blur; Rust's ``FINE_SHELL`` / ``FINE_COLOUR_STEP``).
FINE_SHELL = 200.0
FINE_COLOUR_STEP = 0.1


def needs_fine(values: np.ndarray) -> np.ndarray:
    """(bricks,) bool: the bricks of ``values`` (bricks, k+1, k+1, k+1, 4) a two-level field makes
    fine: those a surface crosses, and those in the shell under one whose colour has an edge."""
    v = values.reshape(values.shape[0], -1, 4).astype(np.float64)
    sigma = v[..., 0]
    crossed = (sigma.max(axis=1) > CROSSED_DENSE) & (sigma.min(axis=1) < CROSSED_SOLID)
    dense = (sigma > CROSSED_DENSE)[..., None]
    rgb = v[..., 1:] / colour_weight(sigma)[..., None]
    span = np.where(dense, rgb, -np.inf).max(axis=1) - np.where(dense, rgb, np.inf).min(axis=1)
    colour_edge = (np.nan_to_num(span, neginf=0.0) > FINE_COLOUR_STEP).any(axis=1)
    return crossed | ((sigma.min(axis=1) < FINE_SHELL) & colour_edge)


def two_level_index(index: np.ndarray, fine: np.ndarray) -> np.ndarray:
    """The two-level index of a one-level ``index`` whose bricks ``fine`` (bricks,) are made fine:
    coarse bricks renumbered 0..N_c in cell order, then the fine ones (as the GPU's bake does)."""
    out = np.full(index.shape, -1, np.int64)
    flat, cells = index.ravel(), out.reshape(-1)
    order = np.argsort(flat)
    in_order = order[flat[order] >= 0]  # cells in brick order
    is_fine = fine[flat[in_order]]
    coarse_cells, fine_cells = in_order[~is_fine], in_order[is_fine]
    cells[coarse_cells] = np.arange(len(coarse_cells))
    cells[fine_cells] = len(coarse_cells) + np.arange(len(fine_cells))
    return out


def split_levels(index: np.ndarray, n_coarse: int) -> tuple[np.ndarray, np.ndarray]:
    """A two-level ``index`` as two one-level ones: the coarse bricks' (0..N_c, -1 elsewhere) and
    the fine bricks' (0..N_f, -1 elsewhere)."""
    coarse = np.where((index >= 0) & (index < n_coarse), index, -1)
    fine = np.where(index >= n_coarse, index - n_coarse, -1)
    return coarse, fine


def colour_weight(sigma_raw: np.ndarray) -> np.ndarray:
    """The colour weight of points with raw density ``sigma_raw``: :data:`COLOUR_FLOOR` plus
    ``clamp(sigma_raw / COLOUR_RAMP, 0, 1)``."""
    return COLOUR_FLOOR + np.clip(np.asarray(sigma_raw, np.float64) / COLOUR_RAMP, 0.0, 1.0)


def brick_points(index: np.ndarray, k: int) -> np.ndarray:
    """Plane coordinates (bricks, k+1, k+1, k+1, 3) of every brick point, in brick order."""
    g = index.shape[0]
    order = np.argsort(index.ravel())
    cells = order[index.ravel()[order] >= 0]
    ijk = np.stack(np.unravel_index(cells, index.shape), axis=-1)  # (bricks, 3)
    abc = np.stack(np.meshgrid(*[np.arange(k + 1)] * 3, indexing="ij"), axis=-1)  # (k+1, k+1, k+1, 3)
    grid = ijk[:, None, None, None, :] * k + abc[None]
    return grid * (2.0 / (g * k)) - 1.0


def decode_at(tri: TriplaneData, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The float64 decoder at plane coordinates ``q`` (..., 3): raw density (...) and RGB, its first
    three features, not premultiplied (..., 3)."""
    world = q * (0.5 * tri.box_warp)
    feat = sample_triplane(tri.planes.astype(np.float64), world.reshape(1, -1, 3), box_warp=tri.box_warp)
    sigma_raw, out = decode(feat, tri.w0, tri.b0, tri.w1, tri.b1)
    return sigma_raw.reshape(q.shape[:-1]), out[..., :3].reshape(*q.shape[:-1], 3)


def decode_brick_points(tri: TriplaneData, index: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`decode_at` every brick point of ``index``: raw density (bricks, k+1, k+1, k+1) and RGB
    (bricks, k+1, k+1, k+1, 3)."""
    return decode_at(tri, brick_points(index, k))


def field_values(sigma_raw: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """What the field stores for decoded points, in float64 (..., 4): the raw density and the RGB
    times its :func:`colour_weight`. The weight is that of the raw density as stored (rounded to
    float16), as the lookup recomputes it."""
    weight = colour_weight(sigma_raw.astype(np.float16))
    return np.concatenate([sigma_raw[..., None], rgb * weight[..., None]], axis=-1)


def bake_reference(tri: TriplaneData, index: np.ndarray, k: int) -> np.ndarray:
    """The field's values in float64 (bricks, k+1, k+1, k+1, 4): :func:`field_values` at every brick
    point of ``index``."""
    return field_values(*decode_brick_points(tri, index, k))


def baked_lookup(
    index: np.ndarray,
    values: np.ndarray,
    k: int,
    box_warp: float,
    points: np.ndarray,
    fine_values: np.ndarray | None = None,
    fine_k: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """``(sigma_raw (...), rgb (..., 3))`` at world ``points`` (..., 3): trilinear inside the point's
    cell (edge cells clamped, so they stand for everything beyond), the RGB as the interpolated
    premultiplied RGB over the interpolated colour weight; :data:`EMPTY_RAW` and 0 in a cell without
    a brick. A two-level field gives ``fine_values`` and ``fine_k`` too."""
    if not fine_k:
        return _lookup_level(index, values, k, box_warp, points)
    coarse, fine = split_levels(index, len(values))
    sigma_c, rgb_c = _lookup_level(coarse, values, k, box_warp, points)
    sigma_f, rgb_f = _lookup_level(fine, np.asarray(fine_values), fine_k, box_warp, points)
    in_fine = _brick_at(fine, box_warp, points) >= 0
    return np.where(in_fine, sigma_f, sigma_c), np.where(in_fine[..., None], rgb_f, rgb_c)


def _cells(g: int, box_warp: float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where world ``points`` (..., 3) fall in a field of G³ cells: their position in cell units and
    their cell (edge cells clamped, so they stand for everything beyond), both float (..., 3)."""
    s = (np.asarray(points, np.float64) * (2.0 / box_warp) + 1.0) * (0.5 * g)
    return s, np.clip(np.floor(s), 0, g - 1)


def _brick_at(index: np.ndarray, box_warp: float, points: np.ndarray) -> np.ndarray:
    """The brick number (or -1) of the cell around each world point (...)."""
    cell = _cells(index.shape[0], box_warp, points)[1].astype(np.int64)
    return index[cell[..., 0], cell[..., 1], cell[..., 2]]


def _lookup_level(
    index: np.ndarray, values: np.ndarray, k: int, box_warp: float, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`baked_lookup` in a one-level field."""
    s, cell = _cells(index.shape[0], box_warp, points)
    local = np.clip((s - cell) * k, 0.0, k)
    i0 = np.minimum(np.floor(local), k - 1)
    f = local - i0
    cell, i0 = cell.astype(np.int64), i0.astype(np.int64)
    brick = index[cell[..., 0], cell[..., 1], cell[..., 2]]
    full = values.astype(np.float64)
    safe = np.maximum(brick, 0)
    acc = np.zeros((*brick.shape, 4))
    weight = np.zeros(brick.shape)
    for corner in range(8):
        d = np.array([corner & 1, (corner >> 1) & 1, corner >> 2])
        w = np.prod(np.where(d == 1, f, 1.0 - f), axis=-1)
        at = i0 + d
        point = full[safe, at[..., 0], at[..., 1], at[..., 2]]
        acc += w[..., None] * point
        weight += w * colour_weight(point[..., 0])
    empty = brick < 0
    sigma_raw = np.where(empty, EMPTY_RAW, acc[..., 0])
    rgb = np.where(empty[..., None], 0.0, acc[..., 1:] / weight[..., None])
    return sigma_raw, rgb


def render_baked_reference(
    tri: TriplaneData,
    index: np.ndarray,
    values: np.ndarray,
    k: int,
    camera: np.ndarray,
    settings: RenderSettings,
    *,
    fine_values: np.ndarray | None = None,
    fine_k: int = 0,
) -> dict[str, np.ndarray]:
    """:func:`lp3d.render.reference.render_reference` with every sample looked up in the field
    instead of decoded (the same sampler and compositing); ``rgb``, ``depth`` and ``weights_sum``. A
    two-level field gives ``fine_values`` and ``fine_k`` too."""

    def evaluate(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points = o[:, None, :] + t[..., None] * d[:, None, :]
        sigma_raw, rgb = baked_lookup(index, values, k, tri.box_warp, points, fine_values, fine_k)
        return sigma_raw, rgb

    out = render_with(tri, camera, settings, evaluate)
    del out["features"]  # the three RGB channels, as out["rgb"]
    return out


# ------------------------------------------------------------------------------------------ the file

#: ``format`` of a saved baked field (``save_baked``).
BAKED_FORMAT = "lp3d-baked-field-v3"  # v2 had one level; v1 stored RGB not premultiplied
#: Older formats :func:`load_baked` still reads (one level, fine_subdivisions 0).
ONE_LEVEL_FORMAT = "lp3d-baked-field-v2"
#: The numbers a saved field holds besides its arrays.
SCALARS = ("subdivisions", "occupancy_epsilon", "max_delta")
#: Largest cells per axis a file may claim (the occupancy grid's limit).
MAX_CELLS = 512


def triplane_digest(triplane: Any) -> str:
    """SHA-256 of what a baked field was decoded from: the planes and decoder as float32 (C order) and
    the box width, so that a field saved for one triplane is refused for another."""
    h = hashlib.sha256()
    for name in ("planes", "w0", "b0", "w1", "b1"):
        h.update(np.ascontiguousarray(np.asarray(getattr(triplane, name), np.float32)).tobytes())
    h.update(np.float32(triplane.box_warp).tobytes())
    return h.hexdigest()


def save_baked(path: str | os.PathLike[str], field: Any, triplane: Any) -> Path:
    """Write ``field`` (an ``lp3d_render.BakedField`` of ``triplane``) to ``path`` (.npz, atomically),
    with the triplane's digest; :func:`load_baked` puts it back on the GPU without baking again."""
    out = Path(path)
    arrays = {
        "format": np.array(BAKED_FORMAT),
        "triplane_sha256": np.array(triplane_digest(triplane)),
        "subdivisions": np.array(field.subdivisions, np.int64),
        "occupancy_epsilon": np.array(field.occupancy_epsilon, np.float64),
        "max_delta": np.array(field.max_delta, np.float64),
        "index": field.index.astype(np.int64),
        "values": field.values,
        "fine_subdivisions": np.array(field.fine_subdivisions, np.int64),
        "fine_values": field.fine_values,
    }
    with atomic_path(out) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return out


#: Largest baked-field file read (its biggest legal arrays, a 512³ index and the bricks, are each
#: within :data:`lp3d.render.npz_reader.MAX_ENTRY_BYTES`).
MAX_FILE_BYTES = 4 << 30
#: Longest text entry (``format``, ``triplane_sha256``).
_MAX_TEXT_CHARS = 64
#: Per key: accepted ``.npy`` dtypes and dimensions (None: a 0-d text).
_ENTRIES: dict[str, tuple[tuple[str, ...], int] | None] = {
    "format": None,
    "triplane_sha256": None,
    "subdivisions": (("<i4", "<i8", "<f4", "<f8"), 0),
    "occupancy_epsilon": (("<f2", "<f4", "<f8", "<i4", "<i8"), 0),
    "max_delta": (("<f2", "<f4", "<f8", "<i4", "<i8"), 0),
    "fine_subdivisions": (("<i4", "<i8", "<f4", "<f8"), 0),
    "index": (("<i4", "<i8"), 3),
    "values": (("<f2",), 5),
    "fine_values": (("<f2",), 5),
}
#: Integer settings: the largest value read before the renderer's own range check (a 10³⁰⁰ would
#: otherwise reach it as an int that overflows).
_INT_SCALARS = ("subdivisions", "fine_subdivisions")


def _check_entry(key: str, h: npz_reader.NpyHeader) -> None:
    """One entry's ``.npy`` header against the baked-field format, before its data is read."""
    NpzError, shape_text = npz_reader.NpzError, npz_reader.shape_text
    if key not in _ENTRIES:
        raise NpzError(key, f"unknown key (a baked field holds {', '.join(_ENTRIES)})")
    spec, got = _ENTRIES[key], f"{h.descr} {shape_text(h.shape)}"
    if spec is None:
        if h.unicode_chars is None or h.unicode_chars > _MAX_TEXT_CHARS:
            raise NpzError(key, f"must be a string of at most {_MAX_TEXT_CHARS} characters, got {got}")
        return
    dtypes, ndim = spec
    if ndim == 0 and (h.descr not in dtypes or h.shape != ()):
        raise NpzError(key, f"must be one finite number, got {got}")
    if h.descr not in dtypes or len(h.shape) != ndim:
        raise NpzError(key, f"must be a {ndim}-d array of {' or '.join(dtypes)}, got {got}")
    if key == "index" and (len(set(h.shape)) != 1 or not 1 <= h.shape[0] <= MAX_CELLS):
        raise NpzError(key, f"must be (G, G, G) with 1 <= G <= {MAX_CELLS}, got {shape_text(h.shape)}")
    if key in ("values", "fine_values"):
        _, a, b, c, four = h.shape
        if not (a == b == c >= 1) or four != 4:  # (0, 1, 1, 1, 4): a one-level field's fine_values
            raise NpzError(key, f"must be (bricks, k+1, k+1, k+1, 4) float16, got {got}")


def _read_field_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The arrays of the baked-field file at ``path``, through the project's bounded ``.npz`` reader:
    a regular file (a FIFO or a device is refused at once), every size checked before it is
    allocated, every header against :data:`_ENTRIES`. OSError for a file that cannot be opened,
    ValueError naming the file (and the key) for its content."""
    where = os.fspath(path)
    file, size = npz_reader.open_regular_file(path, "a baked-field .npz")
    with file:
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{where}: {size} bytes, more than a baked field's cap of {MAX_FILE_BYTES}")
        try:
            return npz_reader.read_npz(file, size, _check_entry)
        except npz_reader.NpzError as e:
            if e.key:
                raise ValueError(f"{where}: {e.key}: {e.message}") from None
            raise ValueError(f"{where}: not a baked-field .npz ({e.message})") from None
        except (OSError, zipfile.BadZipFile, EOFError) as e:  # a read failing mid-way
            raise ValueError(f"{where}: truncated or corrupt file ({type(e).__name__}: {e})") from None


def load_baked(path: str | os.PathLike[str], triplane: Any) -> Any:
    """The baked field saved at ``path`` for ``triplane`` (an ``lp3d_render.Triplane``), attached to its
    GPU copy (later renders with its settings look it up); a ``ValueError`` naming the file and the
    field for anything that does not fit, the renderer's own checks included (no pickle is ever
    loaded; the file is read by :mod:`lp3d.render.npz_reader`, bounded before it is read)."""
    import lp3d_render

    where = os.fspath(path)
    data = _read_field_file(path)
    fields = ("format", "triplane_sha256", *SCALARS, "index", "values")
    missing = sorted(set(fields) - set(data))
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    fmt = str(data["format"])
    if fmt == "lp3d-baked-field-v1":
        raise ValueError(f"{where}: format: baked by an older lp3d (RGB not premultiplied); bake again")
    if fmt == ONE_LEVEL_FORMAT:
        data.setdefault("fine_subdivisions", np.array(0, np.int64))
        data.setdefault("fine_values", np.zeros((0, 1, 1, 1, 4), np.float16))
    elif fmt != BAKED_FORMAT:
        raise ValueError(f"{where}: format {fmt[:40]!r}, expected {BAKED_FORMAT!r}")
    elif "fine_subdivisions" not in data or "fine_values" not in data:
        raise ValueError(f"{where}: missing fine_subdivisions or fine_values")
    if str(data["triplane_sha256"]) != triplane_digest(triplane):
        raise ValueError(f"{where}: baked for other planes or another decoder than this triplane's")
    numbers = {name: _scalar(data[name], f"{where}: {name}") for name in (*SCALARS, "fine_subdivisions")}
    for name in _INT_SCALARS:
        value = numbers[name]
        if value != int(value) or abs(value) > 2**31:
            raise ValueError(f"{where}: {name}: must be a whole number of sub-cells, got {value:g}")
    index = data["index"].astype(np.int64)
    n_bricks = len(data["values"]) + len(data["fine_values"])
    if n_bricks > index.size:
        raise ValueError(f"{where}: {n_bricks} bricks for {index.size} cells")
    try:
        return lp3d_render.attach_baked(
            triplane,
            index,
            np.ascontiguousarray(data["values"]).view(np.uint16),
            subdivisions=int(numbers["subdivisions"]),
            occupancy_epsilon=numbers["occupancy_epsilon"],
            max_delta=numbers["max_delta"],
            fine_subdivisions=int(numbers["fine_subdivisions"]),
            fine_values=np.ascontiguousarray(data["fine_values"]).view(np.uint16),
        )
    except (ValueError, TypeError) as e:  # the renderer's checks of the arrays and numbers
        raise ValueError(f"{where}: {e}") from None


def _scalar(a: Any, what: str) -> float:
    """A 0-d finite number from a file, or a ValueError saying ``what`` it should have been."""
    a = np.asarray(a)
    if a.shape != () or a.dtype.kind not in "iuf" or not np.isfinite(a):
        raise ValueError(f"{what}: must be one finite number, got {a.dtype} {a.shape}")
    return float(a)
