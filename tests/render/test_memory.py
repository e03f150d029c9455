"""Device memory per frame does not depend on the sample count (no per-sample buffers), and the
triplane's device copy is what its planes and decoder take (bench/memory.py reports the numbers)."""

from __future__ import annotations

import numpy as np

import lp3d_render
from support.scenes import make_scene


def test_device_bytes_independent_of_sample_count(gpu) -> None:
    scene = make_scene(size=(32, 32), seed=1)
    cam = lp3d_render.look_at_camera()
    seen = set()
    for s, n in [(4, 4), (12, 12), (48, 0), (64, 64)]:
        lp3d_render.render(
            scene.native, cam, resolution=16, depth_resolution=s, depth_resolution_importance=n
        )
        seen.add((lp3d_render.last_frame_device_bytes(), scene.native.device_bytes))
    assert len(seen) == 1, seen
    frame, tri = seen.pop()
    # Outputs (32 features + depth + weights sum per pixel) twice (storage + readback), plus uniforms.
    assert 2 * 34 * 16 * 16 * 4 <= frame < 2 * 34 * 16 * 16 * 4 + 4096
    planes = 3 * 32 * 32 * 32 * 4
    assert planes <= tri < planes + 32768  # + the decoder uniform (~17 KB)


def test_device_bytes_scale_with_resolution_and_outputs(gpu) -> None:
    scene = make_scene(size=(32, 32), seed=1)
    cam = lp3d_render.look_at_camera()
    sizes = {}
    for r, outputs in [(8, None), (16, None), (16, ["rgb"])]:
        lp3d_render.render(
            scene.native,
            cam,
            resolution=r,
            depth_resolution=4,
            depth_resolution_importance=4,
            outputs=outputs,
        )
        sizes[(r, outputs is None)] = lp3d_render.last_frame_device_bytes()
    assert sizes[(16, True)] > sizes[(8, True)] and sizes[(16, False)] < sizes[(16, True)]
    assert np.isclose(sizes[(16, True)] / sizes[(8, True)], 4.0, rtol=0.05)
