"""``lp3d.nets.superres_onnx``: a package's SR network read back from its ONNX file into torch, as
``--refine`` fits through it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
from lp3d.lift.model_package import load_model_package
from lp3d.nets.superres_onnx import read_superres_onnx


def test_the_shipped_network_reads_back_as_its_checkpoints_own() -> None:
    pkg = load_model_package(DEFAULT_MODEL)
    assert pkg.superres is not None
    net = read_superres_onnx(pkg.superres.path)
    cfg = net.config
    assert (cfg.in_channels, cfg.input_resolution, cfg.output_resolution) == (
        pkg.superres.in_channels,
        pkg.superres.input_resolution,
        pkg.superres.output_resolution,
    )
    # The torch checkpoint beside the package folds its own SR module: the same numbers.
    folded = load_encoder(DEFAULT_MODEL.with_suffix(".pt"), "torch", superres=True).superres
    x = np.random.default_rng(3).standard_normal((1, cfg.in_channels, 64, 64)).astype(np.float32)
    with torch.no_grad():
        got = net(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(got, folded(x), atol=1e-5)
    # Gradients reach the feature image (the refine's use), the weights stay frozen.
    f = torch.from_numpy(x).requires_grad_(True)
    net(f).abs().mean().backward()
    assert f.grad is not None and float(f.grad.abs().sum()) > 0
    assert not any(p.requires_grad for p in net.parameters())


def test_files_that_are_not_a_folded_network_are_refused(tmp_path) -> None:
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not protobuf at all \\x00\\xff" * 10)
    with pytest.raises(ValueError, match="junk.onnx: not a readable ONNX file"):
        read_superres_onnx(junk)
    # A real ONNX graph of another shape: one convolution, no upsampling.
    conv = tmp_path / "conv.onnx"
    torch.onnx.export(
        torch.nn.Conv2d(32, 3, 3, padding=1), (torch.zeros(1, 32, 8, 8),), str(conv), dynamo=False
    )
    with pytest.raises(ValueError, match="conv.onnx: .*(upsampling|not a folded)"):
        read_superres_onnx(conv)
