"""A model package's super-resolution network on the GPU renderer: the WGSL kernels of
``lp3d_render.SuperRes`` (``crates/renderer/src/superres.rs``) with the weights of the package's
``MODEL.superres.onnx``, read by :func:`lp3d.nets.superres_onnx.read_superres_onnx` (which checks the
graph against onnxruntime) and handed over as the folded network's arrays::

    from lp3d.lift.gpu_superres import load_gpu_superres

    sr = load_gpu_superres()                    # the shipped model's, or load_gpu_superres("MODEL.onnx")
    feats = lp3d_render.render(tri, cams, resolution=sr.input_resolution, outputs=["features"])["features"]
    image = sr.apply(feats)                     # (B, 3, R_out, R_out) float32, like onnxruntime's

Needs ``onnx`` and torch to read the file (the ``train`` extra), like ``--refine``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lp3d.lift.inference import DEFAULT_MODEL
from lp3d.lift.model_package import ModelPackageError, load_model_package, verify_superres_file
from lp3d.render.native import native_superres

if TYPE_CHECKING:
    from lp3d.nets.superres import FoldedSuperResolution

__all__ = ["FOLDED_PARTS", "folded_weights", "gpu_superres", "load_gpu_superres"]

#: The folded network's weights, one tensor per ×2 block each (``FoldedSuperResolution``'s names, which
#: ``lp3d_render.SuperRes`` takes as keyword arguments).
FOLDED_PARTS = ("convs_up", "biases_up", "convs", "biases", "rgb_weights", "rgb_biases")


def folded_weights(net: FoldedSuperResolution) -> dict[str, list[np.ndarray]]:
    """The folded network's weights as float32 arrays: name -> one array per block."""
    return {k: [p.detach().cpu().float().numpy() for p in getattr(net, k)] for k in FOLDED_PARTS}


def gpu_superres(net: FoldedSuperResolution) -> Any:
    """``net`` as an ``lp3d_render.SuperRes`` on the renderer's device (its weights copied there)."""
    return native_superres(folded_weights(net), input_resolution=net.config.input_resolution)


def load_gpu_superres(path: str | os.PathLike[str] | None = None) -> Any | None:
    """The super-resolution network of the ONNX model package ``path`` (default: the shipped model) as an
    ``lp3d_render.SuperRes``, or None when the package has none.

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` (a ValueError) for a package or SR file
    that is missing, altered (SHA-256) or does not fit its sidecar entry, and
    :class:`~lp3d.nets.superres_onnx.SuperresOnnxError` (a ValueError) for a graph that is not a folded
    network."""
    from lp3d.nets.superres_onnx import read_superres_onnx

    package = load_model_package(Path(path) if path is not None else DEFAULT_MODEL)
    entry = package.superres
    if entry is None:
        return None
    verify_superres_file(entry)
    net = read_superres_onnx(entry.path)
    cfg = net.config
    got = (cfg.in_channels, cfg.input_resolution, cfg.output_resolution)
    want = (entry.in_channels, entry.input_resolution, entry.output_resolution)
    if got != want:
        raise ModelPackageError(
            f"{entry.path}: the network maps (channels, input, output) {got}, but the package's field "
            f"'superres' says {want}"
        )
    return gpu_superres(net)
