"""What :mod:`lp3d.lift.inference` hands back: :class:`LoadedEncoder` (images -> planes) and
:class:`LoadedSuperres` (feature image -> image), with the checks on their inputs and outputs that
both backends share (:func:`reshape_planes`).

May import :mod:`lp3d.lift.model_package`, :mod:`lp3d.lift.flip_average` and :mod:`lp3d.render`; no
backend (onnxruntime, torch)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from lp3d.lift.flip_average import flip_averaged
from lp3d.lift.model_package import ModelPackage, ModelPackageError
from lp3d.render.settings import N_CHANNELS

Backend = Literal["onnx", "torch"]


@dataclass
class LoadedSuperres:
    """A super-resolution network ready to run: ``sr(features) -> image``.

    ``features`` is the renderer's raw feature image, (B, 32, R, R) or (32, R, R) float32 with
    ``R = input_resolution``; the image is (B, 3, R_out, R_out) (or (3, R_out, R_out)) float32 in about
    [-1, 1] (``lp3d.images.rgb_to_uint8`` clips), ``R_out = output_resolution``. ``package`` is the
    model package it belongs to: its decoder is the one whose features the network was made for.
    ``where`` names the network's file in its errors (``description`` when empty).
    """

    package: ModelPackage
    backend: Backend
    input_resolution: int
    output_resolution: int
    in_channels: int
    description: str
    _run: Callable[[np.ndarray], np.ndarray]
    where: str = ""

    def __call__(self, features: np.ndarray) -> np.ndarray:
        x = np.asarray(features)
        single = x.ndim == 3
        if single:
            x = x[None]
        c, r = self.in_channels, self.input_resolution
        if x.ndim != 4 or x.shape[1:] != (c, r, r):
            raise ValueError(
                f"super-resolution input must be features ({c}, {r}, {r}) or (B, {c}, {r}, {r}) (a raw "
                f"render at resolution={r} with outputs=['features']), got shape {tuple(np.shape(features))}"
            )
        if x.shape[0] == 0:
            raise ValueError("super-resolution input has an empty batch")
        x = np.ascontiguousarray(x, dtype=np.float32)
        if not np.all(np.isfinite(x)):
            raise ValueError("super-resolution input contains NaN/Inf")
        out = np.asarray(self._run(x), dtype=np.float32)
        want = (x.shape[0], 3, self.output_resolution, self.output_resolution)
        if out.shape != want:
            raise ModelPackageError(
                f"{self.where or self.description}: output has shape {out.shape}, expected {want}"
            )
        if not np.all(np.isfinite(out)):
            raise ModelPackageError(f"{self.where or self.description}: produced NaN/Inf")
        return out[0] if single else out

    run = __call__

    def accepts(self, triplane: Any) -> bool:
        """Whether ``triplane`` (a TriplaneData) has this package's decoder and scene bounds, i.e.
        renders the feature space the network was made for."""
        pkg = self.package
        same = all(
            np.array_equal(np.asarray(getattr(triplane, k), np.float32), a)
            for k, a in zip(("w0", "b0", "w1", "b1"), pkg.decoder, strict=True)
        )
        bounds = (float(triplane.box_warp), float(triplane.ray_start), float(triplane.ray_end))
        return same and bounds == (pkg.box_warp, pkg.ray_start, pkg.ray_end)


@dataclass
class LoadedEncoder:
    """An encoder ready to run: ``run(images (B, 3, S, S) float32) -> planes (B, 3, 32, T, T) float32``.

    ``superres`` is the package's super-resolution network when ``load_encoder(..., superres=True)``
    was asked for it and the package has one, else None."""

    package: ModelPackage
    backend: Backend
    run: Callable[[np.ndarray], np.ndarray]
    description: str
    superres: LoadedSuperres | None = None

    def encode(self, images: np.ndarray, *, flip_average: bool = False) -> np.ndarray:
        """``run``, or with ``flip_average`` its flip-averaged form (:mod:`lp3d.lift.flip_average`)."""
        return flip_averaged(self.run, images) if flip_average else self.run(images)


def reshape_planes(out: np.ndarray, batch: int, where: str, resolution: int) -> np.ndarray:
    """Encoder output (B, 3, 32, T, T) or (B, 96, T, T) -> (B, 3, 32, T, T) float32, checked: T must
    be the package's ``resolution`` (its sidecar's ``triplane_resolution``)."""
    out = np.asarray(out, dtype=np.float32)
    if out.ndim == 4 and out.shape[1] == 3 * N_CHANNELS:
        out = out.reshape(out.shape[0], 3, N_CHANNELS, *out.shape[2:])
    t = resolution
    if out.ndim != 5 or out.shape != (batch, 3, N_CHANNELS, t, t):
        raise ModelPackageError(
            f"{where}: output has shape {out.shape}, but the package says ({batch}, 3, 32, {t}, {t})"
        )
    if not np.all(np.isfinite(out)):
        raise ModelPackageError(f"{where}: encoder produced NaN/Inf")
    return out
