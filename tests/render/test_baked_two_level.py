"""Two-level baked fields (docs/baked.md, "Two levels"): the bricks a surface crosses (or a colour edge
under one) baked finer.
The GPU's choice of fine bricks against the rule stated in the reference, both levels' values
against the float64 decoder, two-level renders against the float64 reference of the same lookups,
the saved file, and the arguments refused. Small configs as in tests/render/test_baked.py (32² rays,
12+12 samples, G = 32, k 2 / 4); bench/baked_resolution.py measures the error at the users'
settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import lp3d_render
from lp3d.render.baked import (
    CROSSED_DENSE,
    CROSSED_SOLID,
    bake_reference,
    colour_weight,
    decode_brick_points,
    load_baked,
    needs_fine,
    render_baked_reference,
    save_baked,
    split_levels,
    two_level_index,
)
from lp3d.render.camera import look_at_camera
from lp3d.render.settings import RenderSettings, Skips
from lp3d.render.triplane import TriplaneData
from lp3d.teachers import ProceduralTeacher

S, N, R, G, K, KF = 12, 12, 32, 32, 2, 4
EPS = 1e-6
VIEWS = [(0, 0), (35, -10), (-50, 20)]


@pytest.fixture(scope="module")
def head() -> TriplaneData:
    return ProceduralTeacher(resolution=64).sample(5)


@pytest.fixture(scope="module")
def native(head: TriplaneData, gpu) -> lp3d_render.Triplane:
    return dataclasses.replace(head, occupancy=head.to_native().bake_occupancy(G)).to_native()


@pytest.fixture(scope="module")
def fields(native) -> tuple[lp3d_render.BakedField, lp3d_render.BakedField]:
    """The same head baked with one level (k) and two (k / k_f), for 12 coarse samples."""
    one = lp3d_render.bake(native, subdivisions=K, occupancy_epsilon=EPS, depth_resolution=S)
    two = lp3d_render.bake(
        native, subdivisions=K, fine_subdivisions=KF, occupancy_epsilon=EPS, depth_resolution=S
    )
    return one, two


def test_the_fine_bricks_are_the_ones_needs_fine_picks(fields) -> None:
    """The GPU makes fine exactly the bricks whose k-point values `needs_fine` picks, and numbers the
    coarse bricks first, each level in cell order; the same cells hold bricks as with one level."""
    one, two = fields
    assert (two.subdivisions, two.fine_subdivisions, two.bricks) == (K, KF, one.bricks)
    fine = needs_fine(one.values)
    assert 0 < fine.sum() < len(fine)  # a surface crosses some bricks, not all
    sigma = one.values[..., 0].reshape(len(fine), -1).astype(np.float64)
    crossed = (sigma.max(axis=1) > CROSSED_DENSE) & (sigma.min(axis=1) < CROSSED_SOLID)
    assert (fine & ~crossed).any()  # and a colour edge under one makes some fine too
    assert two.fine_bricks == int(fine.sum())
    assert np.array_equal(two.index, two_level_index(one.index, fine))
    n_coarse = two.bricks - two.fine_bricks
    coarse_index, fine_index = split_levels(two.index, n_coarse)
    assert np.array_equal(coarse_index[coarse_index >= 0], np.arange(n_coarse))
    assert np.array_equal(fine_index[fine_index >= 0], np.arange(two.fine_bricks))


def point(sigma: float, rgb: tuple[float, float, float]) -> list[float]:
    """A stored point: raw density and premultiplied RGB."""
    w = float(colour_weight(np.float64(sigma)))
    return [sigma, *(c * w for c in rgb)]


def test_a_brick_is_fine_where_a_surface_crosses_it_or_its_colour_turns_under_one() -> None:
    """The rule of Rust's ``baked::needs_fine`` unit test, case for case."""
    grey, red = (0.5, 0.5, 0.0), (0.9, 0.5, 0.0)
    cases = [
        ([point(-5, grey), point(20, grey)], True),
        ([point(0, grey), point(60, grey)], True),
        ([point(-5, grey), point(9, grey)], False),  # faint
        ([point(60, grey), point(80, grey)], False),  # under a surface, one colour
        ([point(60, grey), point(80, red)], True),  # under a surface, a colour edge
        ([point(250, grey), point(300, red)], False),  # deep inside: hidden
        ([point(-5, red), point(9, grey)], False),  # the colour of faint points does not count
    ]
    values = np.array([pts for pts, _ in cases], np.float64)[:, :, None, None, :]  # (7, 2, 1, 1, 4)
    assert needs_fine(values).tolist() == [want for _, want in cases]


def test_both_levels_are_the_decoder_rounded_to_float16(head, fields) -> None:
    """Each level's points are the float64 decoder's (raw density and premultiplied RGB), within one
    float16 rounding plus float32's decoder error, as tests/render/test_baked.py holds the one-level field."""
    _, two = fields
    n_coarse = two.bricks - two.fine_bricks
    for got, index, k in zip(
        (two.values, two.fine_values), split_levels(two.index, n_coarse), (K, KF), strict=True
    ):
        assert got.dtype == np.float16 and got.shape == (int((index >= 0).sum()), k + 1, k + 1, k + 1, 4)
        want = bake_reference(head, index, k)
        want[..., 1:] = decode_brick_points(head, index, k)[1] * colour_weight(got[..., 0])[..., None]
        err = np.abs(got.astype(np.float64) - want)
        bound = np.abs(want) * 2.0**-11 + 2.0**-25 + np.array([1e-4, 1e-5, 1e-5, 1e-5])
        assert np.all(err <= bound), (k, float(np.max(err - bound)))


@pytest.mark.parametrize("importance", [0, N])
def test_a_two_level_render_is_the_reference(head, native, fields, importance) -> None:
    """The GPU's lookups in both levels and the float64 reference's, with the field's own float16
    values: to 1e-4. With the importance draw, RGB to 1e-4 + 3 |depth error| (tests/render/test_baked.py
    says why) + twice the reference's own spread when its samples move by float32's rounding: the
    fine bricks follow the decoder's colour across a surface more closely, so a sample moved by
    float32's rounding of the inverse CDF changes it more (one ray of the 3,072 here: depth off by
    3.5e-6, RGB by 1.08e-4; with the colour-edge bricks fine, another: 8.7e-7 and 1.6e-4)."""
    _, two = fields
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in VIEWS])
    skips = Skips(occupancy_epsilon=EPS, baked_subdivisions=K, baked_fine_subdivisions=KF)
    settings = RenderSettings(
        resolution=R, depth_resolution=S, depth_resolution_importance=importance, skips=skips
    )
    outputs = ["rgb", "depth", "weights_sum"]
    got = lp3d_render.render(native, cams, **settings.native_kwargs(), outputs=outputs)
    want = render_baked_reference(
        head,
        two.index,
        two.values,
        K,
        cams,
        dataclasses.replace(settings, skips=Skips()),
        fine_values=two.fine_values,
        fine_k=KF,
    )
    assert float(want["weights_sum"].max()) > 0.9
    for name in ("depth", "weights_sum"):
        np.testing.assert_allclose(got[name], want[name], atol=1e-4, rtol=0, err_msg=name)
    depth_err = np.abs(got["depth"] - want["depth"])[:, None]
    assert (depth_err <= 1e-5).mean() > 0.99
    rgb_err = np.abs(got["rgb"] - want["rgb"])
    bound = 1e-4 + 3.0 * depth_err
    if importance:
        # Where a ray meets a steep surface with a colour edge behind it, moving its samples by
        # float32's rounding moves its RGB ~150x as far as its depth (one ray of the 3,072: depth
        # off by 8.7e-7, RGB by 1.6e-4). Allow twice the reference's own spread when its samples
        # move by one float32 step of t (2.4e-7 at t = 2.8), measured per ray: 11 rays above 5e-5.
        bound = bound + 2.0 * _reference_spread(head, two, cams, settings, shift=2.5e-7)
    assert np.all(rgb_err <= bound), float(np.max(rgb_err - bound))


def _reference_spread(head, two, cams, settings, *, shift: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Per ray and channel, how far the float64 reference's RGB moves when every lookup is moved
    along its ray by Gaussian noise of ``shift`` (the largest of two seeded draws)."""
    from lp3d.render.baked import baked_lookup
    from lp3d.render.reference import render_with

    plain = dataclasses.replace(settings, skips=Skips())
    runs = []
    for seed in (None, 1, 2):
        rng = np.random.default_rng(seed)

        def evaluate(o, d, t, rng=rng, seed=seed):  # type: ignore[no-untyped-def]
            moved = t if seed is None else t + rng.normal(0.0, shift, t.shape)
            points = o[:, None, :] + moved[..., None] * d[:, None, :]
            return baked_lookup(two.index, two.values, K, head.box_warp, points, two.fine_values, KF)

        runs.append(render_with(head, cams, plain, evaluate)["rgb"])
    return np.max([np.abs(r - runs[0]) for r in runs[1:]], axis=0)


def test_the_fine_level_brings_the_render_closer_to_exact_mode(native) -> None:
    """Where the error is (the bricks a surface crosses) the finer points cut it: a k 2 / 4 field is
    nearer exact mode than k 2 alone, and about as near as k 4 everywhere (measured: 29.2, 32.3 and
    32.4 dB)."""
    cam = look_at_camera(yaw_deg=20, pitch_deg=5)
    kw = {"resolution": R, "depth_resolution": S, "depth_resolution_importance": N, "outputs": ["rgb"]}
    exact = lp3d_render.render(native, cam, **kw)["rgb"]

    def psnr(**field: int) -> float:
        rgb = lp3d_render.render(native, cam, **kw, occupancy_epsilon=EPS, **field)["rgb"]
        return float(10 * np.log10(4.0 / np.mean((exact - rgb) ** 2)))

    one, two, four = (
        psnr(baked_subdivisions=K),
        psnr(baked_subdivisions=K, baked_fine_subdivisions=KF),
        psnr(baked_subdivisions=KF),
    )
    assert two > one + 2.0 and two > four - 0.5, (one, two, four)


def test_a_two_level_bakes_progress_only_rises(native, fields) -> None:
    """Until the fine bricks are known the bake counts every brick as fine, so its total falls once
    and the share done never goes back (the viewer's `baking… 43%`); it ends at its total."""
    seen: list[tuple[int, int]] = []
    lp3d_render.bake(
        native,
        subdivisions=K,
        fine_subdivisions=KF,
        occupancy_epsilon=EPS,
        depth_resolution=S,
        progress=lambda d, t: seen.append((d, t)),
    )
    shares = [d / t for d, t in seen]
    assert shares == sorted(shares) and seen[-1][0] == seen[-1][1]
    one, two = fields
    totals = sorted({t for _, t in seen}, reverse=True)
    assert totals == [
        one.bricks * ((K + 1) ** 3 + (KF + 1) ** 3),
        one.bricks * (K + 1) ** 3 + two.fine_bricks * (KF + 1) ** 3,
    ]


def test_a_saved_two_level_field_renders_as_the_baked_one(head, native, fields, tmp_path) -> None:
    """save_baked writes both levels (format v3); load_baked puts them on a fresh copy of the triplane,
    which renders exactly as the baked field; a damaged fine level is refused by name, and a
    one-level file of the previous format still loads."""
    _, two = fields
    path = save_baked(tmp_path / "two.baked.npz", two, native)
    kw = {"resolution": R, "depth_resolution": S, "depth_resolution_importance": N, "outputs": ["rgb"]}
    kw |= {"occupancy_epsilon": EPS, "baked_subdivisions": K, "baked_fine_subdivisions": KF}
    cam = look_at_camera(yaw_deg=-20)
    want = lp3d_render.render(native, cam, **kw)["rgb"]
    second = dataclasses.replace(head, occupancy=native.occupancy).to_native()
    loaded = load_baked(path, second)
    assert (loaded.bricks, loaded.fine_bricks, loaded.bake_seconds) == (two.bricks, two.fine_bricks, 0.0)
    assert np.array_equal(lp3d_render.render(second, cam, **kw)["rgb"], want)
    good = dict(np.load(path, allow_pickle=False))
    damaged = {
        "short": (good | {"fine_values": good["fine_values"][:-1]}, "index: must name bricks"),
        "nan": (good | {"fine_values": np.full_like(good["fine_values"], np.inf)}, "fine_values: NaN or Inf"),
        "k": (good | {"fine_subdivisions": np.array(K)}, "fine_subdivisions"),
        "fraction": (good | {"fine_subdivisions": np.array(4.5)}, "fine_subdivisions: must be a whole"),
        "missing": ({k: v for k, v in good.items() if k != "fine_values"}, "missing fine_subdivisions or"),
    }
    for name, (arrays, words) in damaged.items():
        bad = tmp_path / f"{name}.npz"
        np.savez(bad, **arrays)
        with pytest.raises(ValueError, match=words):
            load_baked(bad, second)
    one_level = lp3d_render.bake(second, subdivisions=K, occupancy_epsilon=EPS, depth_resolution=S)
    v2 = dict(np.load(save_baked(tmp_path / "one.npz", one_level, second), allow_pickle=False))
    v2 = {k: v for k, v in v2.items() if not k.startswith("fine_")}
    v2["format"] = np.array("lp3d-baked-field-v2")
    np.savez(tmp_path / "v2.npz", **v2)
    assert load_baked(tmp_path / "v2.npz", second).fine_subdivisions == 0


def test_bad_two_level_arguments_are_named(native) -> None:
    cam = look_at_camera()
    kw = {"resolution": 8, "depth_resolution": S, "depth_resolution_importance": N, "occupancy_epsilon": EPS}
    with pytest.raises(ValueError, match="baked_fine_subdivisions: must be 0 or in"):
        lp3d_render.render(native, cam, **kw, baked_subdivisions=4, baked_fine_subdivisions=4)
    with pytest.raises(ValueError, match="baked_fine_subdivisions"):
        lp3d_render.render(native, cam, **kw, baked_subdivisions=4, baked_fine_subdivisions=17)
    with pytest.raises(ValueError, match="baked_fine_subdivisions: must be 0 or in"):
        lp3d_render.render(native, cam, **kw, baked_fine_subdivisions=6)
    with pytest.raises(ValueError, match="fine_subdivisions: must be 0 or above subdivisions"):
        lp3d_render.bake(native, subdivisions=4, fine_subdivisions=3)
    with pytest.raises(ValueError, match="baked_fine_subdivisions must be 0 or an int"):
        fine_below = Skips(occupancy_epsilon=EPS, baked_subdivisions=4, baked_fine_subdivisions=2)
        RenderSettings(skips=fine_below).validate()
    with pytest.raises(ValueError, match="baked_fine_subdivisions needs baked_subdivisions > 0"):
        RenderSettings(skips=Skips(occupancy_epsilon=EPS, baked_fine_subdivisions=6)).validate()
