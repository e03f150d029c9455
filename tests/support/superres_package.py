"""The tiny model package with a super-resolution network that the SR tests share
(``tests/lift/test_superres_package.py``, ``tests/lift/test_superres_fit.py``): a randomly perturbed
network, the package built around it, and an inference-weights file of its encoder."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from lp3d.export.package import package_superres
from lp3d.lift.model_package import set_package_superres
from lp3d.nets.superres import SuperresConfig, SuperResolution
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane
from support.tiny_model import tiny_onnx_package

#: The tolerance for onnxruntime against torch.
ONNX_TOLERANCE = 1e-3
#: The CLI tests' SR: 16² raw feature renders -> 64² images.
SR_IN, SR_OUT = 16, 64


def random_sr(config: SuperresConfig, seed: int = 0) -> SuperResolution:
    """A network with every weight perturbed (EG3D's init leaves biases at zero and styles at one)."""
    torch.manual_seed(seed)
    sr = SuperResolution(config)
    with torch.no_grad():
        for p in sr.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return sr.eval()


def cli_sr_config() -> SuperresConfig:
    return SuperresConfig(
        name="test", input_resolution=SR_IN, output_resolution=SR_OUT, block_channels=(8, 8), w_dim=8
    )


def superres_package(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """The tiny ONNX stand-in model with a super-resolution network (16² -> 64²) in its sidecar, the
    same model without one, the network itself, and a sphere triplane with the model's decoder."""
    folder = tmp_path_factory.mktemp("pkg")
    onnx_path, enc, tri, bounds = tiny_onnx_package(folder)
    plain = tmp_path_factory.mktemp("plain")
    for f in folder.iterdir():
        shutil.copy(f, plain / f.name)
    sr = random_sr(cli_sr_config())
    entry, err = package_superres(sr, onnx_path, about={"source": "test"})
    assert err <= ONNX_TOLERANCE
    set_package_superres(onnx_path, entry)
    sphere = folder / "sphere.npz"
    save_triplane(sphere, coloured_sphere(size=32, radius=0.3))
    return {"onnx": onnx_path, "plain": plain / "tiny.onnx", "sr": sr, "sphere": sphere, "encoder": enc}


def weights_file(encoder: torch.nn.Module, path: Path, **extra: object) -> dict[str, object]:
    """An inference-weights file (``lp3d export --weights``'s layout) of the tiny encoder with the
    sphere's decoder; returns its contents."""
    tri = coloured_sphere(size=8)
    data = {
        "format": "lp3d-encoder-weights-v1",
        "config": encoder.config.to_dict(),
        "encoder": encoder.state_dict(),
        "plane_offset": None,
        "decoder": {k: torch.from_numpy(getattr(tri, k)) for k in ("w0", "b0", "w1", "b1")},
        "bounds": {"box_warp": tri.box_warp, "ray_start": tri.ray_start, "ray_end": tri.ray_end},
        **extra,
    }
    torch.save(data, path)
    return data
