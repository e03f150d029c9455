"""The WGSL renderer against the independent float64 NumPy reference (lp3d.render.reference).

Tolerances (float32 kernel vs float64 reference): max abs error <= 1e-4 on features, rgb and depth,
<= 1e-5 on weights_sum. Sizes are small so lavapipe keeps the suite fast; the kernel has no size-
specific code paths (sizes are uniforms), so small cases exercise the same code as large ones.
"""

from __future__ import annotations

import numpy as np
import pytest

import lp3d_render
from lp3d.render.reference import render_reference
from support.scenes import PARITY_CAMERAS, make_scene

FEATURE_TOL = 1e-4
DEPTH_TOL = 1e-4
WEIGHTS_TOL = 1e-5
SAMPLES = {"depth_resolution": 12, "depth_resolution_importance": 12}


def assert_parity(got: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> None:
    assert set(got) == {"features", "rgb", "depth", "weights_sum"}
    for key, tol in [
        ("features", FEATURE_TOL),
        ("rgb", FEATURE_TOL),
        ("depth", DEPTH_TOL),
        ("weights_sum", WEIGHTS_TOL),
    ]:
        assert got[key].shape == ref[key].shape, key
        assert got[key].dtype == np.float32, key
        err = float(np.abs(got[key].astype(np.float64) - ref[key]).max())
        assert err <= tol, f"{key}: max abs error {err:.3e} > {tol:.0e}"


@pytest.mark.parametrize("decoder", ["realistic", "strong"])
@pytest.mark.parametrize("plane_size", [64, 256])
def test_batch_of_all_cameras(gpu, decoder: str, plane_size: int) -> None:
    scene = make_scene(size=(plane_size, plane_size), decoder=decoder, seed=plane_size)
    cams = np.stack(list(PARITY_CAMERAS.values()))
    got = lp3d_render.render(scene.native, cams, resolution=17, **SAMPLES)
    ref = render_reference(scene.data, cams, resolution=17, **SAMPLES)
    assert_parity(got, ref)
    # The strong decoder must really produce both opaque and see-through rays.
    if decoder == "strong":
        assert ref["weights_sum"].max() > 0.85 and ref["weights_sum"].min() < 0.01


@pytest.mark.parametrize("name", list(PARITY_CAMERAS))
def test_single_camera_r1(gpu, name: str) -> None:
    scene = make_scene(decoder="strong", seed=3)
    cam = PARITY_CAMERAS[name]
    got = lp3d_render.render(scene.native, cam, resolution=1, **SAMPLES)
    ref = render_reference(scene.data, cam, resolution=1, **SAMPLES)
    assert got["features"].shape == (32, 1, 1)
    assert_parity(got, ref)


@pytest.mark.parametrize("decoder", ["realistic", "strong"])
def test_resolution_64(gpu, decoder: str) -> None:
    scene = make_scene(size=(256, 256), decoder=decoder, seed=11)
    cams = np.stack([PARITY_CAMERAS["rolled"], PARITY_CAMERAS["off-centre"]])
    got = lp3d_render.render(scene.native, cams, resolution=64, **SAMPLES)
    ref = render_reference(scene.data, cams, resolution=64, **SAMPLES)
    assert_parity(got, ref)


def test_non_square_planes_and_eg3d_sample_counts(gpu) -> None:
    scene = make_scene(size=(48, 80), decoder="strong", seed=5)
    cam = PARITY_CAMERAS["yaw-45"]
    kw = {"resolution": 9, "depth_resolution": 48, "depth_resolution_importance": 48}
    assert_parity(lp3d_render.render(scene.native, cam, **kw), render_reference(scene.data, cam, **kw))


def test_jittered_mode_matches_reference_rng(gpu) -> None:
    scene = make_scene(decoder="strong", seed=8)
    cams = np.stack([PARITY_CAMERAS["frontal"], PARITY_CAMERAS["pitch+25"]])
    kw = {"resolution": 17, **SAMPLES}
    got = lp3d_render.render(scene.native, cams, deterministic=False, seed=1234, **kw)
    ref = render_reference(scene.data, cams, deterministic=False, seed=1234, **kw)
    assert_parity(got, ref)
    det = render_reference(scene.data, cams, **kw)
    assert np.abs(det["features"] - ref["features"]).max() > 1e-3, "jitter should change the render"


def test_coarse_only_and_white_back(gpu) -> None:
    scene = make_scene(decoder="strong", seed=9)
    cam = PARITY_CAMERAS["frontal"]
    for kw in [
        {"depth_resolution": 16, "depth_resolution_importance": 0},
        {"depth_resolution": 2, "depth_resolution_importance": 0},
        {"depth_resolution": 12, "depth_resolution_importance": 12, "white_back": True},
    ]:
        got = lp3d_render.render(scene.native, cam, resolution=17, **kw)
        assert_parity(got, render_reference(scene.data, cam, resolution=17, **kw))


def test_float16_planes_render_their_float32_values(gpu) -> None:
    scene = make_scene(decoder="realistic", seed=2, dtype=np.float16)
    assert scene.native.planes.dtype == np.float16
    cam = PARITY_CAMERAS["yaw+45"]
    got = lp3d_render.render(scene.native, cam, resolution=17, **SAMPLES)
    assert_parity(got, render_reference(scene.data, cam, resolution=17, **SAMPLES))


def test_other_scene_bounds(gpu) -> None:
    # Shapenet-like bounds: box_warp 1.6, rays from 0.1 to 2.6 (the camera is closer).
    scene = make_scene(decoder="strong", seed=4, box_warp=1.6, ray_start=0.1, ray_end=2.6)
    cam = PARITY_CAMERAS["pitch-25"]
    got = lp3d_render.render(scene.native, cam, resolution=17, **SAMPLES)
    assert_parity(got, render_reference(scene.data, cam, resolution=17, **SAMPLES))


@pytest.mark.parametrize("decoder", ["realistic", "strong"])
@pytest.mark.parametrize("plane_size", [64, 256])
def test_parity_scenes_are_well_conditioned(decoder: str, plane_size: int) -> None:
    """The parity scenes must be answerable in float32: a 2e-7 camera shift (float32 rounding of a
    camera at radius 2.7) moves the float64 render by well under the tolerances. Without this, a
    parity failure could be the scene's fault rather than the renderer's."""
    cams = np.stack(list(PARITY_CAMERAS.values()))
    shifted = cams.copy()
    shifted[:, [3, 7, 11]] += 2e-7
    kw = {"resolution": 17, **SAMPLES}
    scene = make_scene(size=(plane_size, plane_size), decoder=decoder, seed=plane_size)
    a = render_reference(scene.data, cams, **kw)
    b = render_reference(scene.data, shifted, **kw)
    assert np.abs(a["features"] - b["features"]).max() < FEATURE_TOL / 5
    assert np.abs(a["weights_sum"] - b["weights_sum"]).max() < WEIGHTS_TOL / 1.5
