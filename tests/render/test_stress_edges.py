"""Hand-picked extremes of the renderer's numerics, against the float64 reference with the tolerance
derived as ``tests/render/test_stress.py`` explains: empty and opaque scenes, densities and logits
spanning decades, tiny depth ranges, extreme focal lengths, cameras inside the box and far away, rays
parallel to the planes, float16 planes at their limits, and weights_sum in dense fog."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lp3d.render.camera import look_at_camera
from support.stress import (
    KW,
    TOL,
    axis_camera,
    build,
    check_scene,
    decoder_at_samples,
    make_decoder,
    make_planes,
    render_gpu,
    render_ref,
    span_decoder,
)

# ------------------------------------------------------------------------------------ hand-picked


def test_empty_and_opaque_scenes_render_their_limits(gpu) -> None:
    rng = np.random.default_rng(7)
    planes = make_planes("smooth", rng, 16, 1.0)
    cameras = np.stack([look_at_camera(), look_at_camera(yaw_deg=-60.0), look_at_camera(pitch_deg=45.0)])
    s = KW["depth_resolution"]
    dec = make_decoder(rng)
    for seed in (None, 99):
        # All empty: density bias -1e4, so softplus(sigma_raw - 1) underflows to exactly 0.
        empty = build(planes, {**dec, "b1": np.r_[-1e4, dec["b1"][1:]]})
        got, ref, _ = check_scene(empty, cameras, seed=seed, well_conditioned=True)
        assert np.all(got["weights_sum"] == 0.0)
        assert np.all(got["features"] == -1.0)
        # No weight: EG3D's NaN -> +inf -> clamp gives every ray the batch-global maximum depth.
        assert np.all(got["depth"] == got["depth"].max())
        if seed is None:
            assert got["depth"].max() == np.float32(3.3)
        else:
            assert got["depth"].max() > np.float32(3.3)
        np.testing.assert_allclose(got["depth"], ref["depth"], rtol=0, atol=TOL)
        # All opaque: density bias +1e4, so the first interval has alpha = 1.
        opaque = build(planes, {**dec, "b1": np.r_[1e4, dec["b1"][1:]]})
        got, ref, _ = check_scene(opaque, cameras, seed=seed, well_conditioned=True)
        np.testing.assert_allclose(got["weights_sum"], 1.0, rtol=0, atol=1e-6)
        step = (3.3 - 2.25) / (s - 1)
        if seed is None:
            # The first fine sample sits at the first coarse midpoint: depth = ray_start + step / 4.
            np.testing.assert_allclose(got["depth"], 2.25 + step / 4, rtol=0, atol=TOL)
        else:
            assert got["depth"].max() <= 2.25 + 2 * step


def test_raw_densities_span_1e4(gpu) -> None:
    rng = np.random.default_rng(11)
    cameras = np.stack([look_at_camera(), look_at_camera(yaw_deg=30.0, pitch_deg=15.0)])
    planes = make_planes("smooth", rng, 16, 1.0)
    for density, logits in [((-1e4, 1e4), 3.0), ((-1e4, -1e3), 3.0), ((1e3, 1e4), 3.0), ((-1e4, 1e4), 1e3)]:
        scene = span_decoder(planes, make_decoder(rng), cameras, KW, density=density, logit_span=logits)
        _, out = decoder_at_samples(scene.data, cameras, {**KW, "depth_resolution_importance": 0})
        assert out[..., 0].min() == pytest.approx(density[0], rel=1e-3)
        assert out[..., 0].max() == pytest.approx(density[1], rel=1e-3)
        assert np.abs(out[..., 1:]).max() == pytest.approx(logits, rel=1e-3)
        got, _, _ = check_scene(scene, cameras)
        if density[1] <= -1e3:
            assert np.all(got["weights_sum"] == 0.0)


def test_feature_logits_span_1e3(gpu) -> None:
    rng = np.random.default_rng(12)
    cameras = np.stack([look_at_camera(), look_at_camera(yaw_deg=-30.0)])
    planes = make_planes("smooth", rng, 16, 1.0)
    scene = span_decoder(planes, make_decoder(rng), cameras, KW, density=(-20.0, 40.0), logit_span=1e3)
    got, _, _ = check_scene(scene, cameras)
    # Saturated sigmoids: the features of opaque rays come close to +-1.
    assert got["features"].max() > 0.9 and got["features"].min() < -0.9


@pytest.mark.parametrize("length", [1e-4, 1e-3])
def test_tiny_depth_range(gpu, length: float) -> None:
    rng = np.random.default_rng(13)
    camera = look_at_camera()
    planes = make_planes("smooth", rng, 16, 1.0)
    bounds = {"ray_start": 2.6, "ray_end": 2.6 + length}
    # Densities of order 1 / length, so the short range holds a visible amount of opacity.
    scene = span_decoder(
        planes, make_decoder(rng), camera, KW, density=(0.0, 2.0 / length), logit_span=3.0, **bounds
    )
    got, ref, _ = check_scene(scene, camera)
    assert ref["weights_sum"].max() > 0.3


@pytest.mark.parametrize("focal", [0.5, 100.0])
def test_extreme_focal_lengths(gpu, focal: float) -> None:
    rng = np.random.default_rng(14)
    cameras = np.stack(
        [look_at_camera(focal=focal), look_at_camera(yaw_deg=20.0, roll_deg=30.0, focal=focal)]
    )
    planes = make_planes("smooth", rng, 16, 1.0)
    scene = span_decoder(planes, make_decoder(rng), cameras, KW, density=(-30.0, 30.0), logit_span=3.0)
    check_scene(scene, cameras, well_conditioned=True)


def test_camera_inside_the_box(gpu) -> None:
    """Cameras at the origin (and off-centre) inside the box, ray_start 0: every ray starts inside."""
    rng = np.random.default_rng(15)
    dirs = [
        ((0, 0, -1), (0, -1, 0)),
        ((1, 0, 0), (0, -1, 0)),
        ((0, -1, 0), (0, 0, 1)),
        ((0, 1, 0), (0, 0, -1)),
    ]
    cameras = [axis_camera(f, d, (0, 0, 0), distance=0.0, focal=0.5) for f, d in dirs]
    cameras.append(look_at_camera(yaw_deg=30.0, radius=0.2, lookat=(0.05, -0.1, 0.0), focal=0.5))
    cameras = np.stack(cameras)
    bounds = {"ray_start": 0.0, "ray_end": 0.9}
    planes = make_planes("smooth", rng, 16, 1.0)
    scene = span_decoder(
        planes, make_decoder(rng), cameras, KW, density=(-5.0, 15.0), logit_span=3.0, **bounds
    )
    got, _, _ = check_scene(scene, cameras, well_conditioned=True)
    assert got["weights_sum"].max() > 0.1


def test_camera_far_away(gpu) -> None:
    """Radius 1e3 with a depth range of +-0.9 around the box. Float32 depths near 1e3 are 6e-5 apart
    and ray directions cancel to ~3e-5 rad (0.03 across the box), so only a scene that does not vary
    across the rays is answerable to ~1e-4: axis-aligned cameras (exact directions) through constant
    planes, whose only edges are box faces the rays cross head-on. An oblique camera through smooth
    planes is judged by its (large, measured) tolerance."""
    rng = np.random.default_rng(16)
    kw = {**KW, "resolution": 9}
    bounds = {"ray_start": 1e3 - 0.9, "ray_end": 1e3 + 0.9}
    axis = np.stack(
        [
            axis_camera((0, 0, -1), (0, -1, 0), (0, 0, 0), distance=1e3, focal=100.0),
            axis_camera((-1, 0, 0), (0, -1, 0), (0, 0.1, 0.2), distance=1e3, focal=100.0),
        ]
    )
    for density in [(-1.0, 3.0), (-10.0, 20.0)]:
        planes = make_planes("constant", rng, 8, 1.0)
        scene = span_decoder(planes, make_decoder(rng), axis, kw, density=density, logit_span=3.0, **bounds)
        _, ref, tol = check_scene(scene, axis, kw)
        assert ref["weights_sum"].max() > 0.9
        assert max(tol["features"], tol["weights_sum"]) < 5e-4, tol
        assert tol["depth"] < 2e-3, tol
    oblique = look_at_camera(yaw_deg=-35.0, pitch_deg=20.0, radius=1e3, lookat=(0, 0, 0), focal=100.0)
    planes = make_planes("smooth", rng, 8, 1.0)
    scene = span_decoder(
        planes, make_decoder(rng), oblique, kw, density=(-1.0, 3.0), logit_span=3.0, **bounds
    )
    _, ref, _ = check_scene(scene, oblique, kw)
    assert ref["weights_sum"].max() > 0.5


def test_rays_parallel_to_the_planes(gpu) -> None:
    """Axis-aligned cameras (exact rotations): the centre ray of each (resolution 9) runs exactly along
    a world axis, so it is parallel to two planes' sampling directions and sees one fixed (u, v) on
    the third, with that (u, v) on a texel centre (fx = 0), a texel edge (fx = 0.5), the plane border
    (u = 1) or the end of the zero-padding fade (u = 1 + 1/W, all taps outside)."""
    rng = np.random.default_rng(17)
    kw = {**KW, "resolution": 9}
    w = 8  # texel centre k at u = (2k + 1) / W - 1; world coordinate = u / 2 for box_warp 1
    centre, edge, border, outside = 1.5 / w, 0.0, 0.5, 0.5 * (1 + 1 / w)
    cameras = np.stack(
        [
            axis_camera((0, 0, -1), (0, -1, 0), (centre, centre, 0)),
            axis_camera((0, 0, 1), (0, -1, 0), (edge, -centre, 0)),
            axis_camera((1, 0, 0), (0, -1, 0), (0, centre, edge)),
            axis_camera((-1, 0, 0), (0, -1, 0), (0, border, -centre)),
            axis_camera((0, -1, 0), (0, 0, 1), (centre, 0, edge)),
            axis_camera((0, 1, 0), (0, 0, -1), (outside, 0, centre)),
            axis_camera((0, 0, -1), (0, -1, 0), (border, -border, 0)),
        ]
    )
    for kind in ("smooth", "noise"):
        planes = make_planes(kind, rng, w, 1.0)
        scene = span_decoder(planes, make_decoder(rng), cameras, kw, density=(-10.0, 20.0), logit_span=3.0)
        got, ref, _ = check_scene(scene, cameras, kw)
        # The centre rays themselves (exact directions, exact texel coordinates) meet TOL outright.
        c = kw["resolution"] // 2
        for key in ("features", "weights_sum"):
            err = np.abs(got[key][..., c, c] - ref[key][..., c, c]).max()
            assert err <= TOL, f"{kind} {key}: centre-ray error {err:.3e}"


def test_float16_planes_at_their_limits(gpu) -> None:
    rng = np.random.default_rng(18)
    cameras = np.stack([look_at_camera(), look_at_camera(yaw_deg=50.0, pitch_deg=-10.0)])
    # +-65504 (float16 max) and nearby large values: decoder pre-activations of order 1e4 to 1e5.
    big = rng.choice(np.array([-65504.0, -6e4, -3.2e4, 3.2e4, 6e4, 65504.0]), size=(3, 32, 8, 8))
    scene = build(big.astype(np.float16), make_decoder(rng))
    assert np.abs(scene.data.planes).max() == np.float16(65504)
    check_scene(scene, cameras)
    # float16 subnormals (k * 2^-24, |k| < 1024) must reach the decoder unflushed: w0 is scaled up so
    # they carry the whole signal (if they were flushed to 0 only the biases would remain).
    sub = (rng.integers(-1023, 1024, size=(3, 32, 16, 16)) * 2.0**-24).astype(np.float16)
    assert np.abs(sub).max() < np.finfo(np.float16).smallest_normal
    dec = make_decoder(rng)
    dec["w0"] *= 2.0**24 / 600
    scene = span_decoder(sub, dec, cameras, KW, density=(-10.0, 20.0), logit_span=3.0)
    flushed = dataclasses.replace(scene.data, planes=np.zeros_like(sub))
    got, ref, _ = check_scene(scene, cameras, well_conditioned=True)
    assert np.abs(render_ref(flushed, cameras, KW)["features"] - ref["features"]).max() > 100 * TOL


# ------------------------------------------------------------------------ weights_sum above 1


def test_weights_sum_stays_at_most_one_in_dense_fog(gpu) -> None:
    """A fog whose raw density is ~35 +- a few everywhere, at EG3D's 48+48: every ray ends nearly opaque
    after ~95 moderate alphas. Before the kernel clamped it, the float32 running sum of weights ended
    above 1 on ~480 of these 2048 rays, by up to 4 ulps (1.0000005). The float64 value stays below
    1 + K 1e-10, i.e. 1.0 in float32, and the output must not exceed it."""
    rng = np.random.default_rng(2)
    dec = make_decoder(rng)
    dec["w1"][0] *= 2.0
    dec["b1"][0] = 35.0
    scene = build(make_planes("noise", rng, 16, 1.0), dec)
    cameras = np.stack([look_at_camera(), look_at_camera(yaw_deg=40.0, pitch_deg=-20.0)])
    kw = {"resolution": 32, "depth_resolution": 48, "depth_resolution_importance": 48}
    got = render_gpu(scene, cameras, kw)  # checks weights_sum <= 1
    ref = render_ref(scene.data, cameras, {**kw, "resolution": 8})
    k = kw["depth_resolution"] + kw["depth_resolution_importance"] - 1
    assert ref["weights_sum"].max() <= 1.0 + k * 1e-10 and np.float32(1.0 + k * 1e-10) == 1.0
    assert got["weights_sum"].min() > 0.999 and ref["weights_sum"].min() > 0.999
