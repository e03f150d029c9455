"""A model package's super-resolution weights file, ``MODEL.superres.npz``: the folded network
(``lp3d.nets.superres.FoldedSuperResolution``, whose every layer is a plain convolution) as float32
arrays, beside the package's ``MODEL.superres.onnx``. The renderer reads it
(``lp3d_renderer::SuperresWeights::load``, ``lp3d_render.SuperRes.load``) so that the GPU's
super-resolution, in Python, in the viewer and on the share page, needs neither ONNX nor PyTorch.

Keys (``docs/model-package.md``): ``format_version`` (1), ``input_resolution``, and for each ×2 block
``i`` the arrays ``convs_up_i``, ``biases_up_i``, ``convs_i``, ``biases_i``, ``rgb_weights_i``,
``rgb_biases_i`` (:data:`FOLDED_PARTS`). The sidecar records its SHA-256 (``superres.weights_sha256``).

Needs numpy only."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lp3d.atomic import atomic_path

if TYPE_CHECKING:
    from lp3d.nets.superres import FoldedSuperResolution

__all__ = ["FOLDED_PARTS", "WEIGHTS_FORMAT_VERSION", "folded_weights", "superres_weights_path"]
__all__ += ["write_superres_weights"]

#: The folded network's weights, one tensor per ×2 block each (``FoldedSuperResolution``'s names,
#: which ``lp3d_render.SuperRes`` takes as keyword arguments).
FOLDED_PARTS = ("convs_up", "biases_up", "convs", "biases", "rgb_weights", "rgb_biases")
#: The file's version (``WEIGHTS_FORMAT_VERSION`` in ``crates/renderer/src/superres/file.rs``).
WEIGHTS_FORMAT_VERSION = 1


def superres_weights_path(onnx_path: str | os.PathLike[str]) -> Path:
    """The weights file beside a package's ``MODEL.superres.onnx``: ``MODEL.superres.npz``."""
    return Path(onnx_path).with_suffix(".npz")


def folded_weights(net: FoldedSuperResolution) -> dict[str, list[np.ndarray]]:
    """The folded network's weights as float32 arrays: name -> one array per block."""
    return {k: [p.detach().cpu().float().numpy() for p in getattr(net, k)] for k in FOLDED_PARTS}


def write_superres_weights(
    path: str | os.PathLike[str], weights: Mapping[str, Sequence[np.ndarray]], *, input_resolution: int
) -> Path:
    """Write ``weights`` (:func:`folded_weights`) for feature images of side ``input_resolution``,
    atomically. The renderer's reader checks every shape when the file is loaded."""
    if sorted(weights) != sorted(FOLDED_PARTS):
        raise ValueError(f"weights must hold exactly {FOLDED_PARTS}, got {sorted(weights)}")
    n = len(weights["convs_up"])
    if n == 0 or any(len(weights[k]) != n for k in FOLDED_PARTS):
        raise ValueError("weights must hold one array per ×2 block for every part, and at least one block")
    arrays: dict[str, np.ndarray] = {
        "format_version": np.array(WEIGHTS_FORMAT_VERSION, dtype=np.int64),
        "input_resolution": np.array(int(input_resolution), dtype=np.int64),
    }
    for part in FOLDED_PARTS:
        for i, a in enumerate(weights[part]):
            arrays[f"{part}_{i}"] = np.ascontiguousarray(a, dtype=np.float32)
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)  # stored, not compressed: what the renderer's reader takes
    return path
