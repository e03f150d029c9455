"""``lp3d_render.render(..., superres=)``: the feature images super-resolved in the render's own command
buffers give the same images as rendering, reading the features back and applying the network to them
(the same kernels on the same inputs: bit for bit), match onnxruntime within the WGSL network's tolerance,
leave the render's other outputs untouched, and refuse a network that cannot read the render."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

import lp3d_render
from lp3d.lift.gpu_superres import gpu_superres, load_gpu_superres
from lp3d.lift.inference import DEFAULT_MODEL
from lp3d.lift.model_package import load_model_package
from lp3d.nets.superres import FoldedSuperResolution, SuperresConfig, SuperResolution
from lp3d.render.camera import look_at_camera
from lp3d.teachers import ProceduralTeacher

#: Most the WGSL network may differ from onnxruntime on the same float32 input (as in test_superres_wgsl).
TOLERANCE = 1e-3
SAMPLES = {"depth_resolution": 12, "depth_resolution_importance": 12}


@pytest.fixture(scope="module")
def head():
    return ProceduralTeacher().sample(3).to_native()


def _small_network(input_resolution: int = 16):
    torch.manual_seed(4)
    cfg = SuperresConfig(
        name="t",
        input_resolution=input_resolution,
        output_resolution=4 * input_resolution,
        block_channels=(24, 12),
        w_dim=8,
    )
    return gpu_superres(FoldedSuperResolution(SuperResolution(cfg).eval()))


def test_chained_equals_render_then_apply_bit_for_bit(gpu, head) -> None:
    sr = _small_network()
    cams = np.stack([look_at_camera(yaw_deg=y) for y in (-25, 0, 30)])
    chained = lp3d_render.render(head, cams, resolution=16, superres=sr, **SAMPLES)
    plain = lp3d_render.render(head, cams, resolution=16, **SAMPLES)
    assert chained["image"].shape == (3, 3, 64, 64) and chained["image"].dtype == np.float32
    np.testing.assert_array_equal(chained["image"], sr.apply(plain["features"]))
    for name in ("features", "rgb", "depth", "weights_sum"):
        np.testing.assert_array_equal(chained[name], plain[name], err_msg=name)
    # One camera without a batch axis, and only the image's neighbours asked for.
    one = lp3d_render.render(head, cams[1], resolution=16, superres=sr, outputs=["depth"], **SAMPLES)
    assert sorted(one) == ["depth", "image"]
    np.testing.assert_array_equal(one["image"], chained["image"][1])


def test_the_shipped_network_chained_matches_onnxruntime(gpu, head) -> None:
    sr = load_gpu_superres()
    entry = load_model_package(DEFAULT_MODEL).superres
    assert entry is not None
    cam = look_at_camera(yaw_deg=20, pitch_deg=-5)
    out = lp3d_render.render(head, cam, resolution=sr.input_resolution, superres=sr, **SAMPLES)
    session = ort.InferenceSession(str(entry.path), providers=["CPUExecutionProvider"])
    want = session.run(None, {session.get_inputs()[0].name: out["features"][None]})[0][0]
    err = float(np.abs(out["image"] - want).max())
    assert out["image"].shape == (3, 256, 256)
    assert err <= TOLERANCE, f"onnxruntime differs by {err}"


def test_a_network_that_cannot_read_the_render_is_refused(gpu, head) -> None:
    sr = _small_network()
    cam = look_at_camera()
    with pytest.raises(ValueError, match=r"resolution=16, got 32"):
        lp3d_render.render(head, cam, resolution=32, superres=sr, **SAMPLES)
    with pytest.raises(ValueError, match="baked field holds density and RGB only"):
        lp3d_render.render(
            head, cam, resolution=16, superres=sr, occupancy_epsilon=1e-3, baked_subdivisions=2, **SAMPLES
        )
    with pytest.raises(TypeError, match="superres: expected an lp3d_render.SuperRes, got str"):
        lp3d_render.render(head, cam, resolution=16, superres="small.superres.onnx", **SAMPLES)
    # None is no network.
    assert "image" not in lp3d_render.render(head, cam, resolution=16, superres=None, **SAMPLES)
