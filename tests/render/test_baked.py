"""The baked field (docs/baked.md): the GPU's bake against the float64 decoder, its brick layout
against the rule it states, baked renders against the float64 reference of the same lookups, and
the arguments it refuses. Small configs (32² rays, 12+12 samples, G = 16) keep lavapipe fast; the
speed and the error against exact mode are measured in bench/baked.py, not here."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import lp3d_render
from lp3d.render.baked import (
    COLOUR_FLOOR,
    COLOUR_RAMP,
    EMPTY_RAW,
    bake_reference,
    baked_lookup,
    colour_weight,
    decode_brick_points,
    render_baked_reference,
)
from lp3d.render.camera import look_at_camera
from lp3d.render.settings import RenderSettings, Skips
from lp3d.render.triplane import TriplaneData
from lp3d.teachers import ProceduralTeacher

S, N, R, G, K = 12, 12, 32, 32, 2
EPS = 1e-6
#: (yaw, pitch) of the views the baked renders are checked in.
VIEWS = [(0, 0), (35, -10), (-50, 20)]


@pytest.fixture(scope="module")
def head() -> TriplaneData:
    return ProceduralTeacher(resolution=64).sample(5)


@pytest.fixture(scope="module")
def native(head: TriplaneData, gpu) -> lp3d_render.Triplane:
    """The head with its own G = 32 occupancy grid (the default 64 would make the test slow)."""
    plain = head.to_native()
    return dataclasses.replace(head, occupancy=plain.bake_occupancy(G)).to_native()


@pytest.fixture(scope="module")
def field(native: lp3d_render.Triplane) -> lp3d_render.BakedField:
    """Baked for 48 coarse samples: intervals shorter than a cell, so the reach is one cell."""
    return lp3d_render.bake(native, subdivisions=K, occupancy_epsilon=EPS, depth_resolution=48)


def max_delta(t: TriplaneData, s: int) -> float:
    return (t.ray_end - t.ray_start) / (s - 1)


def test_the_bricks_are_the_occupied_cells_and_their_reach(native, head, field) -> None:
    """A cell holds a brick iff an occupied cell (bound above the skip's threshold) lies within one
    sample interval of it on every axis; bricks are numbered in cell order."""
    assert (field.subdivisions, field.cells, field.occupancy_epsilon) == (K, G, pytest.approx(EPS))
    # RenderSettings.max_interval: one coarse step, with a few ulps of slack for float32 rounding.
    assert field.max_delta == pytest.approx(max_delta(head, 48), abs=1e-5)
    threshold = 1.0 + math.log(math.expm1(EPS / field.max_delta))
    occupied = native.occupancy.astype(np.float64) > threshold
    reach = math.ceil(field.max_delta / (head.box_warp / G))
    kept = occupied.copy()
    for axis in range(3):
        grown = np.zeros_like(kept)
        for shift in range(-reach, reach + 1):
            src = [slice(None)] * 3
            dst = [slice(None)] * 3
            src[axis] = slice(max(0, -shift), G - max(0, shift))
            dst[axis] = slice(max(0, shift), G - max(0, -shift))
            grown[tuple(dst)] |= kept[tuple(src)]
        kept = grown
    index = field.index
    assert index.shape == (G, G, G) and np.array_equal(index >= 0, kept)
    assert 0 < field.bricks == int(kept.sum()) < G**3
    assert np.array_equal(index[kept], np.arange(field.bricks))  # cell order


def test_the_bake_is_the_decoder_rounded_to_float16(head, field) -> None:
    """Every stored point is the float64 decoder's raw density and premultiplied RGB at that point,
    within one float16 rounding plus float32's decoder error (1e-4 on the raw density, a sum of 64
    terms that can cancel, as in the renderer's own tests; 1e-5 on RGB, after the sigmoid)."""
    got = field.values
    assert got.dtype == np.float16 and got.shape == (field.bricks, K + 1, K + 1, K + 1, 4)
    want = bake_reference(head, field.index, K)
    # The colour weight is the stored raw density's: where float32 rounded the raw density to the
    # other neighbouring float16, the premultiplied RGB follows the GPU's (the raw is checked here too).
    sigma_raw, rgb = decode_brick_points(head, field.index, K)
    want[..., 1:] = rgb * colour_weight(got[..., 0])[..., None]
    err = np.abs(got.astype(np.float64) - want)
    half_ulp = np.abs(want) * 2.0**-11 + 2.0**-25  # relative; the subnormal step below 2^-14
    f32 = np.array([1e-4, 1e-5, 1e-5, 1e-5])
    assert np.all(err <= half_ulp + f32), float(np.max(err - half_ulp - f32))
    assert np.any(want[..., 0] > 5.0) and np.any(want[..., 0] < -5.0)  # surfaces and empty space


def _baked_and_reference(head, native, importance: int) -> tuple[dict, dict]:
    """The GPU's baked render (three views) and the float64 reference with the same field (its float16
    values read back), with ``importance`` samples after S coarse ones."""
    field = lp3d_render.bake(native, subdivisions=K, occupancy_epsilon=EPS, depth_resolution=S)
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in VIEWS])
    baked = Skips(occupancy_epsilon=EPS, baked_subdivisions=K)
    settings = RenderSettings(
        resolution=R, depth_resolution=S, depth_resolution_importance=importance, skips=baked
    )
    outputs = ["rgb", "depth", "weights_sum"]
    got = lp3d_render.render(native, cams, **settings.native_kwargs(), outputs=outputs)
    exact_settings = dataclasses.replace(settings, skips=Skips())
    want = render_baked_reference(head, field.index, field.values, K, cams, exact_settings)
    assert float(want["weights_sum"].max()) > 0.9  # the head is in view
    return got, want


def test_a_baked_render_is_the_reference_lookup(head, native) -> None:
    """Coarse samples only (at the same depths in both): the same lookups and compositing, to 1e-4."""
    got, want = _baked_and_reference(head, native, importance=0)
    for name in ("rgb", "depth", "weights_sum"):
        np.testing.assert_allclose(got[name], want[name], atol=1e-4, rtol=0, err_msg=name)


def test_a_baked_render_with_the_importance_draw_is_the_reference(head, native) -> None:
    """With the importance draw (from the baked densities): depth and opacity to 1e-4 everywhere, RGB
    to 1e-4 on every ray whose draw float32 and float64 agree on (depths within 1e-5: all but a few
    rays). On the others float32's rounding of the inverse CDF moves samples by up to ~7e-5; at a
    surface the colour changes ~2 per unit depth, which the bound 1e-4 + 3 |depth error| allows for
    (one ray of the 3,072 here: depth off by 5.3e-5, RGB by 1.0e-4; before the colour was
    premultiplied, 8.2e-5)."""
    got, want = _baked_and_reference(head, native, importance=N)
    for name in ("depth", "weights_sum"):
        np.testing.assert_allclose(got[name], want[name], atol=1e-4, rtol=0, err_msg=name)
    depth_err = np.abs(got["depth"] - want["depth"])[:, None]
    agree = depth_err <= 1e-5
    assert agree.mean() > 0.99
    rgb_err = np.abs(got["rgb"] - want["rgb"])
    assert np.all(rgb_err[np.broadcast_to(agree, rgb_err.shape)] <= 1e-4), float(rgb_err.max())
    assert np.all(rgb_err <= 1e-4 + 3.0 * depth_err), float(np.max(rgb_err - 3.0 * depth_err))


def test_a_baked_render_is_close_to_exact_mode(native) -> None:
    """Interpolating decoded values instead of decoding interpolated features costs little at k = 4
    on a smooth teacher head (bench/baked.py measures it at the users' settings)."""
    cam = look_at_camera(yaw_deg=20, pitch_deg=5)
    kw = {"resolution": R, "depth_resolution": S, "depth_resolution_importance": N, "outputs": ["rgb"]}
    exact = lp3d_render.render(native, cam, **kw)["rgb"]
    baked = lp3d_render.render(native, cam, **kw, occupancy_epsilon=EPS, baked_subdivisions=4)["rgb"]
    psnr = 10 * np.log10(4.0 / np.mean((exact - baked) ** 2))
    assert psnr > 30.0, psnr


def test_a_transparent_corner_does_not_tint_an_opaque_one() -> None:
    """The lookup un-premultiplies: halfway between an opaque red point and a transparent point of
    any colour, the colour is red (to within the colour floor); between two opaque points, their
    mean; where every corner is transparent, their mean too."""
    k, index = 1, np.zeros((1, 1, 1), np.int64)
    values = np.zeros((1, 2, 2, 2, 4))
    values[0, 0, ..., 0], values[0, 1, ..., 0] = 500.0, -40.0  # opaque at x = -1, transparent at x = 1
    red, green = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    values[0, 0, ..., 1:] = red * colour_weight(500.0)
    values[0, 1, ..., 1:] = green * colour_weight(-40.0)
    assert colour_weight(500.0) > 0.999 and colour_weight(-40.0) == COLOUR_FLOOR
    sigma, rgb = baked_lookup(index, values, k, 2.0, np.zeros((1, 3)))
    assert sigma[0] == pytest.approx(230.0) and np.allclose(rgb[0], red, atol=1.1 * COLOUR_FLOOR)
    values[0, 1, ..., 0], values[0, 1, ..., 1:] = 500.0, green * colour_weight(500.0)
    assert np.allclose(baked_lookup(index, values, k, 2.0, np.zeros((1, 3)))[1][0], [0.5, 0.5, 0.0])
    values[..., 0] = -1e4  # every corner transparent: the plain mean
    values[0, 0, ..., 1:], values[0, 1, ..., 1:] = red * COLOUR_FLOOR, green * COLOUR_FLOOR
    assert np.allclose(baked_lookup(index, values, k, 2.0, np.zeros((1, 3)))[1][0], [0.5, 0.5, 0.0])


def test_a_cell_without_a_brick_is_empty(field, head) -> None:
    g = field.cells
    empty = np.argwhere(field.index < 0)
    assert len(empty) > 0
    centres = (empty + 0.5) * (2.0 / g) - 1.0  # plane coordinates of the empty cells' centres
    sigma, rgb = baked_lookup(field.index, field.values, K, head.box_warp, centres * head.box_warp / 2)
    assert np.all(sigma == EMPTY_RAW) and not rgb.any()


def test_the_bake_reports_progress_and_a_raising_callback_stops_it(native) -> None:
    seen: list[tuple[int, int]] = []
    lp3d_render.bake(native, subdivisions=3, occupancy_epsilon=EPS, progress=lambda d, t: seen.append((d, t)))
    done = [d for d, _ in seen]
    assert done and done[-1] == seen[-1][1] and done == sorted(set(done))

    def stop(done: int, total: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        lp3d_render.bake(native, subdivisions=5, occupancy_epsilon=EPS, progress=stop)
    with pytest.raises(ValueError, match="progress: must be callable"):
        lp3d_render.bake(native, progress=3)


def test_a_saved_field_renders_as_the_baked_one_and_belongs_to_its_triplane(head, tmp_path) -> None:
    """save_baked / load_baked: a field loaded into a fresh copy of the triplane renders exactly as
    the one baked (no second bake); another triplane's file, and damaged files, are refused by name."""
    from lp3d.render.baked import load_baked, save_baked

    first = dataclasses.replace(head, occupancy=head.to_native().bake_occupancy(G)).to_native()
    field = lp3d_render.bake(first, subdivisions=K, occupancy_epsilon=EPS, depth_resolution=S)
    path = save_baked(tmp_path / "head.baked.npz", field, first)
    kw = {"resolution": R, "depth_resolution": S, "depth_resolution_importance": N, "outputs": ["rgb"]}
    kw |= {"occupancy_epsilon": EPS, "baked_subdivisions": K}
    cam = look_at_camera(yaw_deg=-20)
    want = lp3d_render.render(first, cam, **kw)["rgb"]
    second = dataclasses.replace(head, occupancy=first.occupancy).to_native()
    loaded = load_baked(path, second)
    assert (loaded.bricks, loaded.bake_seconds) == (field.bricks, 0.0)
    assert np.array_equal(lp3d_render.render(second, cam, **kw)["rgb"], want)
    other = ProceduralTeacher(resolution=64).sample(6).to_native()
    with pytest.raises(ValueError, match="head.baked.npz: baked for other planes"):
        load_baked(path, other)
    good = dict(np.load(path, allow_pickle=False))
    damaged = {
        "missing": ({k: v for k, v in good.items() if k != "values"}, "missing values"),
        "nan": (good | {"values": np.full_like(good["values"], np.nan)}, "values: NaN or Inf"),
        "index": (good | {"index": np.zeros_like(good["index"])}, "index: must name bricks"),
        "dtype": (good | {"values": good["values"].astype(np.float32)}, "values: must be"),
        "scalar": (good | {"subdivisions": np.array("six")}, "subdivisions: must be one finite number"),
    }
    for name, (arrays, words) in damaged.items():
        bad = tmp_path / f"{name}.npz"
        np.savez(bad, **arrays)
        with pytest.raises(ValueError, match=words):
            load_baked(bad, second)
    older = tmp_path / "v1.npz"
    np.savez(older, **(good | {"format": np.array("lp3d-baked-field-v1")}))
    with pytest.raises(ValueError, match="format: baked by an older lp3d"):
        load_baked(older, second)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a baked-field .npz"):
        load_baked(tmp_path / "junk.npz", second)


def test_one_baked_setting_in_both_languages() -> None:
    import re

    from lp3d.render.settings import BAKED

    # The empty cells' raw density: the WGSL lookup's constant is the reference's.
    source = lp3d_render.shader_sources()["baked.wgsl"]
    (wgsl,) = re.findall(r"const BAKED_EMPTY_RAW: f32 = (-?[0-9.]+);", source)
    assert float(wgsl) == EMPTY_RAW
    (wgsl,) = re.findall(r"const BAKED_COLOUR_RAMP: f32 = ([0-9.]+);", source)
    assert float(wgsl) == COLOUR_RAMP
    (wgsl,) = re.findall(r"const BAKED_COLOUR_FLOOR: f32 = ([0-9.e-]+);", source)
    assert float(wgsl) == COLOUR_FLOOR

    native = lp3d_render._lp3d_render
    assert BAKED.baked_subdivisions == native.BAKED_SUBDIVISIONS
    assert BAKED.baked_fine_subdivisions == native.BAKED_FINE_SUBDIVISIONS
    assert BAKED.occupancy_epsilon == pytest.approx(native.BAKED_OCCUPANCY_EPSILON, rel=1e-7)
    plain = dataclasses.replace(BAKED, occupancy_epsilon=0.0, baked_subdivisions=0, baked_fine_subdivisions=0)
    assert plain == Skips()  # nothing else


def test_bad_baked_arguments_are_named(native) -> None:
    cam = look_at_camera()
    kw = {"resolution": 8, "depth_resolution": S, "depth_resolution_importance": N}
    with pytest.raises(ValueError, match="baked_subdivisions: needs occupancy_epsilon > 0"):
        lp3d_render.render(native, cam, **kw, baked_subdivisions=2)
    with pytest.raises(ValueError, match="baked_subdivisions"):
        lp3d_render.render(native, cam, **kw, occupancy_epsilon=EPS, baked_subdivisions=9)
    with pytest.raises(ValueError, match="outputs: a baked field holds density and RGB only"):
        lp3d_render.render(native, cam, **kw, occupancy_epsilon=EPS, baked_subdivisions=2)
    with pytest.raises(ValueError, match="subdivisions"):
        lp3d_render.bake(native, subdivisions=0)
    with pytest.raises(ValueError, match="occupancy_epsilon"):
        lp3d_render.bake(native, occupancy_epsilon=0.0)
    with pytest.raises(ValueError, match="triplane: expected lp3d_render.Triplane"):
        lp3d_render.bake("head.npz")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="baked_subdivisions needs occupancy_epsilon"):
        RenderSettings(skips=Skips(baked_subdivisions=2)).validate()
    with pytest.raises(ValueError, match="baked_subdivisions must be an int"):
        RenderSettings(skips=Skips(occupancy_epsilon=EPS, baked_subdivisions=True)).validate()  # type: ignore[arg-type]
