"""The shipped model (python/lp3d/lift/models): present in the installed package, within its size budget,
self-consistent across its ONNX and torch forms, and what ``lp3d demo`` and ``lp3d encode`` use."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
from lp3d.lift.model_package import load_model_package

MODELS = DEFAULT_MODEL.parent
#: The weights in the repository within 25 MB (each of the ONNX graph and the torch weights).
MAX_BYTES = 25_000_000


def test_the_shipped_files_exist_and_fit_the_budget() -> None:
    shipped = ("small.onnx", "small.json", "small.pt", "small.superres.onnx", "small.superres.npz")
    shipped += ("small.eval.json", "README.md")
    for name in shipped:
        assert (MODELS / name).is_file(), f"{MODELS / name} is missing from the installed package"
    for name in ("small.onnx", "small.pt"):
        size = (MODELS / name).stat().st_size
        assert size <= MAX_BYTES, f"{name}: {size} bytes > {MAX_BYTES}"


def test_sidecar_describes_the_shipped_configuration() -> None:
    # The shipped model is ``small-colour`` (``small`` with the colour grid).
    pkg = load_model_package(DEFAULT_MODEL)
    assert pkg.config_name == "small-colour" and pkg.image_size == 128 and pkg.triplane_resolution == 64
    assert pkg.model_path == DEFAULT_MODEL
    report = json.loads((MODELS / "small.eval.json").read_text())
    assert report["config"] == "small-colour"
    assert report["student"]["novel_psnr"] > 0 and report["baseline"]["steps"] > 0


def test_onnx_and_float16_torch_weights_agree() -> None:
    pytest.importorskip("torch")
    onnx, half = load_encoder(DEFAULT_MODEL), load_encoder(MODELS / "small.pt")
    np.testing.assert_array_equal(onnx.package.w1, half.package.w1)  # the same decoder in both forms
    assert (onnx.package.box_warp, onnx.package.ray_start, onnx.package.ray_end) == (
        half.package.box_warp,
        half.package.ray_start,
        half.package.ray_end,
    )
    images = np.random.default_rng(0).uniform(-1, 1, (2, 3, 128, 128)).astype(np.float32)
    a, b = onnx.run(images), half.run(images)
    assert np.isfinite(a).all()
    # float16 weights against the float32 graph: ~1e-3 of the range (tests/lift/test_export.py measures it).
    assert np.abs(a - b).max() <= 5e-3 * np.abs(a).max()


def test_the_shipped_super_resolution_matches_its_torch_form() -> None:
    """small.superres.onnx against the same network built from small.pt's float16 state (export's
    parity bound, 1e-3)."""
    pytest.importorskip("torch")
    from lp3d.lift.inference import load_superres

    onnx_sr, torch_sr = load_superres(DEFAULT_MODEL), load_superres(MODELS / "small.pt")
    assert onnx_sr is not None and torch_sr is not None, "the shipped package has no super-resolution"
    features = np.random.default_rng(1).normal(0, 1, (1, 32, 64, 64)).astype(np.float32)
    a, b = onnx_sr(features), torch_sr(features)
    assert a.shape == (1, 3, 256, 256) and np.isfinite(a).all()
    assert np.abs(a - b).max() <= 1e-3


def test_orbit_of_a_shipped_model_head_writes_super_resolved_frames(tmp_path, capsys) -> None:
    """``lp3d orbit`` on a head the shipped model made writes its SR's 256² frames."""
    from PIL import Image

    from lp3d.cli import main
    from lp3d.render.triplane_io import save_triplane

    encoder = load_encoder(DEFAULT_MODEL)
    image = np.random.default_rng(2).uniform(-1, 1, (1, 3, 128, 128)).astype(np.float32)
    save_triplane(tmp_path / "head.npz", encoder.package.triplane(encoder.run(image)[0]))
    code = main(["orbit", str(tmp_path / "head.npz"), "-o", str(tmp_path / "o.gif"), "--frames", "3",
                 "--samples", "8+8"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0
    assert "super-resolved by the shipped model's small.superres.onnx" in out
    gif = Image.open(tmp_path / "o.gif")
    assert gif.n_frames == 3 and gif.size == (256, 256)
