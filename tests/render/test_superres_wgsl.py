"""The super-resolution network in the renderer's WGSL (``lp3d_render.SuperRes``) against the torch
``FoldedSuperResolution`` and onnxruntime: the shipped package's network on random and rendered feature
images, and a network of EG3D's widths (random weights) exported to ONNX and read back as a package's
would be; batching; and the errors that name a bad weight or feature array."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

import lp3d_render
from lp3d.export import export_superres
from lp3d.lift.gpu_superres import gpu_superres, load_gpu_superres
from lp3d.lift.inference import DEFAULT_MODEL
from lp3d.lift.model_package import load_model_package
from lp3d.lift.superres_weights import FOLDED_PARTS, folded_weights
from lp3d.nets.stylegan_ops import LRELU_ALPHA, LRELU_GAIN
from lp3d.nets.superres import FoldedSuperResolution, SuperresConfig, SuperResolution
from lp3d.nets.superres_onnx import read_superres_onnx
from lp3d.render.camera import look_at_camera
from lp3d.render.native import render
from lp3d.teachers import ProceduralTeacher

#: Most the WGSL network may differ from torch or onnxruntime on the same float32 input.
TOLERANCE = 1e-3
SHADER = Path(__file__).resolve().parents[2] / "crates" / "renderer" / "shaders" / "superres.wgsl"


def _onnx(path, x: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(None, {session.get_inputs()[0].name: x})[0]


def _torch(net, x: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return net(torch.from_numpy(x)).numpy()


def _folded(cfg: SuperresConfig) -> FoldedSuperResolution:
    """A network of ``cfg`` with its random initial weights, folded."""
    return FoldedSuperResolution(SuperResolution(cfg).eval())


def test_the_shipped_network_matches_torch_and_onnxruntime(gpu) -> None:
    package = load_model_package(DEFAULT_MODEL)
    assert package.superres is not None
    path = package.superres.path
    sr = load_gpu_superres()
    net = read_superres_onnx(path)
    assert (sr.in_channels, sr.input_resolution, sr.output_resolution) == (32, 64, 256)
    r = sr.input_resolution
    random = np.random.default_rng(0).standard_normal((2, 32, r, r), dtype=np.float32)
    # Rendered heads: a teacher's triplanes through the renderer, as `lp3d render` feeds the network.
    teacher = ProceduralTeacher()
    cams = np.stack([look_at_camera(yaw_deg=20), look_at_camera(yaw_deg=-15, pitch_deg=5)])
    rendered = np.concatenate(
        [render(teacher.sample(s), cams, resolution=r, outputs=["features"])["features"] for s in (0, 1)]
    )
    for name, x in (("random", random), ("rendered", rendered)):
        got = sr.apply(x)
        assert got.shape == (x.shape[0], 3, 256, 256) and got.dtype == np.float32
        for other, want in (("torch", _torch(net, x)), ("onnxruntime", _onnx(path, x))):
            err = float(np.abs(got - want).max())
            assert err <= TOLERANCE, f"{name} features: {other} differs by {err}"
    # One image without a batch axis is the batch's first.
    np.testing.assert_array_equal(sr.apply(rendered[0]), sr.apply(rendered)[0])


def test_eg3d_widths_exported_and_read_back_match(gpu, tmp_path) -> None:
    # EG3D's SuperresolutionHybrid8XDC widths (32 -> 256 -> 128, two ×2 blocks) with its random
    # initial weights; a 32² input keeps the torch and GPU runs short (bench/superres_speed.py times
    # the full 128² -> 512²; the kernels take every size from their uniforms).
    torch.manual_seed(0)
    cfg = SuperresConfig(name="eg3d-widths", input_resolution=32, output_resolution=128)
    assert cfg.block_channels == (256, 128) and cfg.in_channels == 32
    full = SuperResolution(cfg).eval()
    with torch.no_grad():  # EG3D starts its biases at zero; a trained network's are not
        for name, p in full.named_parameters():
            if name.endswith(".bias") and ".affine." not in name:
                p.normal_(0.0, 0.1)
    path = export_superres(full, tmp_path / "eg3d.superres.onnx")
    net = read_superres_onnx(path)
    sr = gpu_superres(net)
    assert (sr.in_channels, sr.input_resolution, sr.output_resolution) == (32, 32, 128)
    x = np.random.default_rng(1).uniform(-1, 1, (2, 32, 32, 32)).astype(np.float32)
    got = sr.apply(x)
    for other, want in (("torch", _torch(net, x)), ("onnxruntime", _onnx(path, x))):
        err = float(np.abs(got - want).max())
        assert err <= TOLERANCE, f"{other} differs by {err}"


def test_a_batch_equals_its_images_one_by_one(gpu) -> None:
    torch.manual_seed(2)
    cfg = SuperresConfig(
        name="t", input_resolution=16, output_resolution=64, block_channels=(24, 12), w_dim=8
    )
    sr = gpu_superres(_folded(cfg))
    x = np.random.default_rng(2).standard_normal((3, 32, 16, 16), dtype=np.float32)
    batch = sr.apply(x)
    for i in range(3):
        np.testing.assert_array_equal(sr.apply(x[i : i + 1])[0], batch[i])


def test_bad_weights_and_features_name_the_field(gpu) -> None:
    cfg = SuperresConfig(name="t", input_resolution=8, output_resolution=32, block_channels=(16, 8), w_dim=8)
    good = folded_weights(_folded(cfg))
    assert sorted(good) == sorted(FOLDED_PARTS)

    def refused(match: str, **change) -> None:
        with pytest.raises(ValueError, match=match):
            lp3d_render.SuperRes(**{**good, **change}, input_resolution=8)

    refused(r"convs\[1\]: shape must be \[8, 8, 3, 3\]", convs=[good["convs"][0], good["convs"][1][:, :4]])
    refused(r"biases_up: expected 2 arrays", biases_up=good["biases_up"][:1])
    nan = [good["rgb_biases"][0], np.array([0.0, np.nan, 0.0], np.float32)]
    refused(r"rgb_biases\[1\]: contains NaN/Inf at flat index 1", rgb_biases=nan)
    refused(
        r"rgb_weights\[0\]: dtype must be one of",
        rgb_weights=[w.astype(np.int32) for w in good["rgb_weights"]],
    )
    refused(r"convs: expected a list of numpy arrays", convs=good["convs"][0])
    refused(
        r"convs_up: expected one array per",
        convs_up=[],
        biases_up=[],
        convs=[],
        biases=[],
        rgb_weights=[],
        rgb_biases=[],
    )
    with pytest.raises(ValueError, match=r"input_resolution: .*output side must be in \[2, 1024\]"):
        lp3d_render.SuperRes(**good, input_resolution=512)
    with pytest.raises(TypeError, match="input_resolution: must be an int"):
        lp3d_render.SuperRes(**good, input_resolution=8.0)

    sr = lp3d_render.SuperRes(**good, input_resolution=8)
    shape = r"features: shape must be \(32, 8, 8\) or \(B, 32, 8, 8\), got \[1, 32, 16, 16\]"
    with pytest.raises(ValueError, match=shape):
        sr.apply(np.zeros((1, 32, 16, 16), np.float32))
    bad = np.zeros((32, 8, 8), np.float32)
    bad[0, 3, 4] = np.inf
    with pytest.raises(ValueError, match="features: contains NaN/Inf at flat index 28"):
        sr.apply(bad)
    huge = {**good, "convs_up": [np.full_like(good["convs_up"][0], 3e38), good["convs_up"][1]]}
    with pytest.raises(ValueError, match="superres: the network overflowed float32"):
        lp3d_render.SuperRes(**huge, input_resolution=8).apply(np.ones((32, 8, 8), np.float32))


def test_the_kernels_activation_is_stylegans() -> None:
    consts = dict(re.findall(r"^const (SR_\w+): \w+ = ([0-9.eu]+);", SHADER.read_text(), re.M))
    assert np.float32(consts["SR_LRELU_SLOPE"]) == np.float32(LRELU_ALPHA)
    assert np.float32(consts["SR_LRELU_GAIN"]) == np.float32(LRELU_GAIN)
    # The page's module (every stage file) carries the kernels too.
    assert lp3d_render.shader_sources()["superres.wgsl"] == SHADER.read_text()
