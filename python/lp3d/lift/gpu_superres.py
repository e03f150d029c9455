"""A model package's super-resolution network on the GPU renderer: the WGSL kernels of
``lp3d_render.SuperRes`` (``crates/renderer/src/superres.rs``) with the weights of the package's
``MODEL.superres.npz`` (:mod:`lp3d.lift.superres_weights`, written at export beside the ONNX graph
and checked against it then)::

    from lp3d.lift.gpu_superres import load_gpu_superres

    sr = load_gpu_superres()                    # the shipped model's, or load_gpu_superres("MODEL.onnx")
    feats = lp3d_render.render(tri, cams, resolution=sr.input_resolution, outputs=["features"])["features"]
    image = sr.apply(feats)                     # (B, 3, R_out, R_out) float32, like onnxruntime's

Needs numpy and the renderer only. :func:`gpu_superres` puts a PyTorch network there."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lp3d.lift.inference import DEFAULT_MODEL
from lp3d.lift.model_package import (
    ModelPackageError,
    SuperresEntry,
    load_model_package,
    verify_superres_weights,
)
from lp3d.lift.superres_weights import folded_weights
from lp3d.render.native import native_superres, renderer

if TYPE_CHECKING:
    from lp3d.nets.superres import FoldedSuperResolution

__all__ = ["gpu_superres", "load_gpu_superres", "shipped_superres_entry", "superres_on_gpu"]


def gpu_superres(net: FoldedSuperResolution) -> Any:
    """``net`` as an ``lp3d_render.SuperRes`` on the renderer's device (its weights copied there)."""
    return native_superres(folded_weights(net), input_resolution=net.config.input_resolution)


def superres_on_gpu(entry: SuperresEntry) -> Any:
    """A package's network (its sidecar ``entry``) as an ``lp3d_render.SuperRes``: the weights file
    checked against its SHA-256, read by the renderer, and its sizes against the entry's.

    Raises :class:`~lp3d.lift.model_package.ModelPackageError` (a ValueError) for a weights file that
    is missing, altered or does not fit the entry; the renderer's reader raises a ValueError naming
    the file and key for one that is not a folded network."""
    verify_superres_weights(entry)
    sr = renderer().SuperRes.load(entry.weights_path)
    got = (sr.in_channels, sr.input_resolution, sr.output_resolution)
    want = (entry.in_channels, entry.input_resolution, entry.output_resolution)
    if got != want:
        raise ModelPackageError(
            f"{entry.weights_path}: the network maps (channels, input, output) {got}, but the package's "
            f"field 'superres' says {want}"
        )
    return sr


def load_gpu_superres(path: str | os.PathLike[str] | None = None) -> Any | None:
    """The super-resolution network of the ONNX model package ``path`` (default: the shipped model) as an
    ``lp3d_render.SuperRes`` (:func:`superres_on_gpu`), or None when the package has none."""
    entry = load_model_package(Path(path) if path is not None else DEFAULT_MODEL).superres
    return None if entry is None else superres_on_gpu(entry)


def shipped_superres_entry(tri: Any) -> SuperresEntry | None:
    """The shipped model's super-resolution entry when ``tri`` (a triplane, or anything with its
    decoder's ``w0``, ``b0``, ``w1``, ``b1``) has the shipped model's decoder (the network was fit on
    that decoder's feature images), else None."""
    from lp3d.lift.model_package import decoder_digest

    package = load_model_package(DEFAULT_MODEL)
    if package.superres is None or decoder_digest(tri) != decoder_digest(package.decoder):
        return None
    return package.superres
