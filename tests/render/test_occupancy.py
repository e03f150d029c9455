"""The occupancy grid skip (docs/occupancy.md): the bake is conservative, rendering with it stays
within the documented bound of exact mode, and the grid round-trips through the .npz with its
checksum. Small configs (32² rays, 12+12 samples) keep lavapipe fast."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.reference import decode, sample_triplane
from lp3d.render.triplane import TriplaneData
from lp3d.render.triplane_io import TriplaneFileError, load_triplane, save_triplane
from lp3d.teachers import ProceduralTeacher
from support.scenes import make_scene

S, N, R = 12, 12, 32
SAMPLES = {"resolution": R, "depth_resolution": S, "depth_resolution_importance": N}


def native(t: TriplaneData, **kw) -> lp3d_render.Triplane:
    return dataclasses.replace(t, **kw).to_native()


@pytest.fixture(scope="module")
def head() -> TriplaneData:
    return ProceduralTeacher(resolution=64).sample(3)


def raw_threshold(eps: float, t: TriplaneData, s: int = S) -> float:
    """The raw density below which a cell is empty (docs/occupancy.md), for deterministic sampling."""
    delta = (t.ray_end - t.ray_start) / (s - 1)
    return 1.0 + math.log(math.expm1(eps / delta))


def cell_of(q: np.ndarray, g: int) -> tuple[np.ndarray, ...]:
    idx = np.clip(np.floor((q + 1.0) * 0.5 * g), 0, g - 1).astype(int)
    return idx[:, 0], idx[:, 1], idx[:, 2]


@pytest.mark.parametrize("scene", ["head", "strong", "realistic"])
def test_bake_is_conservative(head: TriplaneData, scene: str) -> None:
    tri = head if scene == "head" else make_scene(size=(48, 40), decoder=scene, seed=4).data
    g = 16
    grid = native(tri).bake_occupancy(g)
    assert grid.shape == (g, g, g) and grid.dtype == np.float32
    rng = np.random.default_rng(0)
    # Inside the box and beyond it (edge cells stand for the outside), plus cell faces.
    q = rng.uniform(-1.4, 1.4, (60_000, 3))
    faces = -1.0 + 2.0 * rng.integers(0, g + 1, (5_000, 3)) / g
    q = np.concatenate([q, faces, faces + 1e-9, faces - 1e-9])
    sigma, _ = decode(sample_triplane(tri.planes, q * tri.box_warp / 2.0), tri.w0, tri.b0, tri.w1, tri.b1)
    bound = grid[cell_of(q, g)].astype(np.float64)
    assert np.all(sigma <= bound), float((sigma - bound).max())


def test_head_grid_skips_empty_space(head: TriplaneData) -> None:
    grid = native(head).bake_occupancy(32)
    empty = float((grid <= raw_threshold(1e-4, head)).mean())
    assert empty > 0.3, f"only {empty:.1%} of the cells are empty on a teacher head"


def bound_for(m: int, eps: float) -> dict[str, float]:
    """docs/occupancy.md: composite error for m skipped intervals of opacity <= eps."""
    return {"weights_sum": m * eps, "rgb": 2 * 1.001 * 2 * m * eps}


def test_render_within_bound_of_exact(gpu, head: TriplaneData) -> None:
    tri = native(head)
    eps = 1e-4
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=5.0) for y in (0.0, 35.0)])
    exact = lp3d_render.render(tri, cams, **SAMPLES)
    skip = lp3d_render.render(tri, cams, **SAMPLES, occupancy_epsilon=eps)
    bound = bound_for(S + N - 1, eps)
    # The composite bound, plus the importance draw's shift (measured, docs/occupancy.md): the
    # parity tolerance of exact mode.
    for key in ("weights_sum", "rgb"):
        err = float(np.abs(skip[key] - exact[key]).max())
        assert err <= bound[key] + 1e-4, f"{key}: {err:.3e} > {bound[key]:.3e}"
    hit = exact["weights_sum"] > 0.5
    depth_err = np.abs(skip["depth"] - exact["depth"])[hit]
    depth_bound = (head.ray_end - head.ray_start) * 2 * (S + N - 1) * eps / 0.5
    assert float(depth_err.max()) <= depth_bound + 1e-4


def test_coarse_skip(gpu, head: TriplaneData) -> None:
    """Skipping in the coarse pass too moves the importance samples, so its error is measured
    (docs/performance.md, "Exact mode's skips"), not bounded; here: valid outputs and a bounded
    composite without them."""
    tri = native(head)
    cam = look_at_camera(yaw_deg=20.0)
    out = lp3d_render.render(tri, cam, **SAMPLES, occupancy_epsilon=1e-4, occupancy_coarse=True)
    assert all(np.all(np.isfinite(v)) for v in out.values())
    assert 0.0 <= out["weights_sum"].min() and out["weights_sum"].max() <= 1.0
    # Without importance samples the coarse pass is the composite: the bound holds again.
    kw = {"resolution": R, "depth_resolution": 24, "depth_resolution_importance": 0}
    exact = lp3d_render.render(tri, cam, **kw)
    skip = lp3d_render.render(tri, cam, **kw, occupancy_epsilon=1e-4)
    assert float(np.abs(skip["weights_sum"] - exact["weights_sum"]).max()) <= 23 * 1e-4 + 1e-6
    with pytest.raises(ValueError, match="occupancy_coarse"):
        lp3d_render.render(tri, cam, **SAMPLES, occupancy_coarse=True)


def test_exact_mode_unchanged_by_a_grid(gpu, head: TriplaneData) -> None:
    plain = native(head)
    with_grid = native(head, occupancy=plain.bake_occupancy(16))
    cam = look_at_camera(yaw_deg=20.0)
    a = lp3d_render.render(plain, cam, **SAMPLES)
    b = lp3d_render.render(with_grid, cam, **SAMPLES)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_all_empty_scene(gpu, head: TriplaneData) -> None:
    b1 = head.b1.copy()
    b1[0] = -30.0
    w1 = head.w1.copy()
    w1[0] = 0.0
    empty = TriplaneData(planes=np.zeros_like(head.planes), w0=head.w0, b0=head.b0, w1=w1, b1=b1)
    tri = native(empty)
    grid = tri.bake_occupancy(8)
    assert np.all(grid <= raw_threshold(1e-6, empty))
    out = lp3d_render.render(tri, look_at_camera(), **SAMPLES, occupancy_epsilon=1e-6)
    assert np.all(out["weights_sum"] == 0.0)
    assert np.all(out["rgb"] == -1.0)


def test_npz_round_trip(tmp_path, head: TriplaneData) -> None:
    grid = native(head).bake_occupancy(8)
    path = tmp_path / "head.npz"
    save_triplane(path, TriplaneData(**{**vars(head), "occupancy": grid}))
    with np.load(path) as z:
        assert z["occupancy"].shape == (8, 8, 8) and z["occupancy_checksum"].dtype == np.int64
    back = load_triplane(path)
    np.testing.assert_array_equal(back.occupancy, grid)
    # Rust reads the Python file and writes one Python reads.
    rust = lp3d_render.Triplane.load(path)
    np.testing.assert_array_equal(rust.occupancy, grid)
    rust.save(tmp_path / "rust.npz")
    np.testing.assert_array_equal(load_triplane(tmp_path / "rust.npz").occupancy, grid)


def rewrite(path, **changes) -> None:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(path, **arrays)


@pytest.mark.parametrize(
    ("change", "key", "message"),
    [
        ({"occupancy": np.zeros((8, 8, 4), np.float32)}, "occupancy", "(G, G, G)"),
        ({"occupancy": np.zeros((8, 8, 8), np.float64)}, "occupancy", "float32"),
        ({"occupancy": np.full((8, 8, 8), np.nan, np.float32)}, "occupancy", "NaN"),
        ({"occupancy_checksum": None}, "occupancy_checksum", "missing"),
        ({"occupancy_checksum": np.array(12345, np.int64)}, "occupancy_checksum", "another triplane"),
        ({"planes": np.zeros((3, 32, 64, 64), np.float32)}, "occupancy_checksum", "another triplane"),
    ],
)
def test_bad_grid_in_npz(tmp_path, head: TriplaneData, change, key: str, message: str) -> None:
    path = tmp_path / "bad.npz"
    save_triplane(path, TriplaneData(**{**vars(head), "occupancy": native(head).bake_occupancy(8)}))
    rewrite(path, **change)
    with pytest.raises(TriplaneFileError, match=f"'{key}'.*{message}" if key else message):
        load_triplane(path)
    with pytest.raises(ValueError, match=key):
        lp3d_render.Triplane.load(path)


def test_bad_grid_argument(head: TriplaneData) -> None:
    with pytest.raises(ValueError, match="occupancy"):
        native(head, occupancy=np.zeros((4, 4, 5), np.float32))
    with pytest.raises(ValueError, match="occupancy_epsilon"):
        lp3d_render.render(native(head), look_at_camera(), **SAMPLES, occupancy_epsilon=1.5)
