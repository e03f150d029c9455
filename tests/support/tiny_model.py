"""A randomly initialised ``tiny`` encoder exported as an ONNX model package, with the sample
sphere's decoder: the stand-in model of the CLI and media tests (no training, a few seconds)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane import TriplaneData


def tiny_onnx_package(folder: Path) -> tuple[Path, Any, TriplaneData, dict[str, float]]:
    """``(tiny.onnx with its sidecar, the torch encoder, the sphere, its scene bounds)``."""
    import torch

    from lp3d.lift.model_package import save_model_package
    from lp3d.nets.encoder import build_encoder

    torch.manual_seed(0)
    enc = build_encoder("tiny").eval()
    s = enc.config.image_size
    path = Path(folder) / "tiny.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # legacy-exporter deprecation and tracer warnings
        torch.onnx.export(
            enc,
            (torch.zeros(1, 3, s, s),),
            str(path),
            input_names=["image"],
            output_names=["planes"],
            dynamic_axes={"image": {0: "batch"}, "planes": {0: "batch"}},
            dynamo=False,
        )
    tri = coloured_sphere(size=8)
    bounds = {"box_warp": tri.box_warp, "ray_start": tri.ray_start, "ray_end": tri.ray_end}
    save_model_package(path, (tri.w0, tri.b0, tri.w1, tri.b1), enc.config, bounds)
    return path, enc, tri, bounds
