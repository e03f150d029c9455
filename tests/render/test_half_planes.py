"""Float16 planes stay float16 on the device (packed pairs, float32 arithmetic): rendering them
equals rendering the same (float16-rounded) values uploaded as float32, and matches the float64
reference on the rounded planes at the parity tolerance."""

from __future__ import annotations

import numpy as np
import pytest

import lp3d_render
from lp3d.render.reference import render_reference
from support.scenes import PARITY_CAMERAS, make_scene

SAMPLES = {"resolution": 17, "depth_resolution": 12, "depth_resolution_importance": 12}


@pytest.mark.parametrize("decoder", ["realistic", "strong"])
def test_half_planes_match_float32_and_reference(gpu, decoder: str) -> None:
    scene = make_scene(size=(64, 48), decoder=decoder, seed=21, dtype=np.float16)
    d = scene.data
    assert d.planes.dtype == np.float16
    as_f32 = lp3d_render.Triplane(d.planes.astype(np.float32), d.w0, d.b0, d.w1, d.b1)
    cams = np.stack([PARITY_CAMERAS["frontal"], PARITY_CAMERAS["yaw-45"]])
    half = lp3d_render.render(scene.native, cams, **SAMPLES)
    full = lp3d_render.render(as_f32, cams, **SAMPLES)
    for key in half:
        assert float(np.abs(half[key] - full[key]).max()) <= 1e-5, key
    ref = render_reference(d, cams, **SAMPLES)
    for key, tol in [("features", 1e-4), ("depth", 1e-4), ("weights_sum", 1e-5)]:
        assert float(np.abs(half[key] - ref[key]).max()) <= tol, key
    # Half the plane bytes on the device.
    plane_bytes = d.planes.size * 4
    assert as_f32.device_bytes - scene.native.device_bytes == plane_bytes // 2


def test_half_planes_near_their_limits(gpu) -> None:
    """Subnormal, tiny and large float16 values (65504 is the largest) unpack exactly."""
    scene = make_scene(size=(16, 16), decoder="realistic", seed=2)
    d = scene.data
    special = np.array(
        [0.0, -0.0, 6e-8, -6e-8, 3e-5, 6.1e-5, 1.0, -2.5, 1000.0, -65504.0, 65504.0], np.float16
    )
    planes = np.resize(special, d.planes.shape).astype(np.float16)
    planes[:, :, 4:12, 4:12] = d.planes[:, :, 4:12, 4:12] * 0.01  # a mild centre
    w0 = d.w0 * 1e-3  # keep the decoder's input range sane
    half = lp3d_render.Triplane(planes, w0, d.b0, d.w1, d.b1)
    full = lp3d_render.Triplane(planes.astype(np.float32), w0, d.b0, d.w1, d.b1)
    cam = PARITY_CAMERAS["frontal"]
    a = lp3d_render.render(half, cam, **SAMPLES)
    b = lp3d_render.render(full, cam, **SAMPLES)
    for key in a:
        assert np.all(np.isfinite(a[key]))
        np.testing.assert_array_equal(a[key], b[key])
