"""Fitting a lifted head to its own photo: a short optimisation of the encoder's triplane on the input
view (``lp3d encode --refine N``), as the inversion methods the paper compares against do (PTI; the
hybrid encoders GOAE and TriPlaneNet start from an encoder's output too).

The encoder gets the head's shape and rough colours; it misses what its training never showed it.
:func:`refine` starts from its planes and takes ``steps`` Adam steps through the torch twin of the
renderer (:mod:`lp3d.render.torch_twin`) on the input view, with three terms:

* **photo**: L1 between the raw RGB render and the photo (downsampled to ``resolution``), on
  ``rays_per_step`` random rays of the view per step; a quarter of the rays per step makes each
  step 4x cheaper, and over the steps every pixel is seen;
* **mirror** (``mirror``, on by default): the same for the photo flipped left to right, seen from the
  mirrored camera (:func:`~lp3d.lift.pose.mirrored_camera`). Faces are nearly symmetric, so this
  second view is nearly true, and it holds the side of the head that the photo turns away from,
  which a fit to one view would smear with the seen side's colours;
* **prior**: the mean squared change of the planes, in units of each channel's spread in the
  encoder's output, times ``prior_weight``. The input view sees only one side of the head and the
  three planes are shared by all sides, so an unheld fit buys the input view with broken side views;
  the prior keeps what the photo does not ask to change at the encoder's prediction.

Only the planes change: the decoder and scene bounds are the model package's, so the refined head
still renders the feature space its super-resolution network was made for.

The photo's camera is not known: :func:`lp3d.lift.pose.find_camera` fits it first, with the
encoder's planes held fixed (a grid search, then gradient descent on a small move of the camera).

May import :mod:`lp3d.render`; torch is needed (``pip install torch``), onnxruntime is not.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lp3d.lift.pose import (
    camera_at,
    estimate_pose,
    find_camera,
    fit_pose,
    mirrored_camera,
    photo_target,
    render_rgb,
)
from lp3d.lift.refine_settings import MAX_STEPS, RefineSettings
from lp3d.render.camera import camera_summary, validate_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.settings import SceneBounds
from lp3d.render.torch_stages import rays_from_cameras
from lp3d.render.triplane import TriplaneData

__all__ = [
    "MAX_STEPS",
    "RefineResult",
    "RefineSettings",
    "estimate_pose",
    "find_camera",
    "fit_pose",
    "psnr_db",
    "refine",
    "refine_planes",
]


@dataclass
class RefineResult:
    """What :func:`refine` returns: the refined ``triplane`` (the input's decoder, bounds and source,
    with the photo's camera), that ``camera`` (25,) float64 and its yaw and pitch, and the input
    view's PSNR (dB, raw RGB at ``RefineSettings.resolution``, seen from ``camera``) before and after."""

    triplane: TriplaneData
    camera: np.ndarray
    yaw_deg: float
    pitch_deg: float
    psnr_before: float
    psnr_after: float
    seconds: float


def refine_planes(
    planes: Tensor,
    decoder: tuple[Tensor, ...],
    bounds: SceneBounds,
    image: np.ndarray | Tensor,
    camera: Tensor,
    settings: RefineSettings,
    *,
    on_step: Callable[[], Any] | None = None,
) -> Tensor:
    """``planes`` (3, 32, T, T) float32 fitted to ``image`` (3, S, S) seen from ``camera`` (25,) by
    :class:`RefineSettings` (module docstring); returns new planes, the input untouched."""
    r = settings.resolution
    photo = photo_target(image, r)
    views = [(photo, camera.float())]
    if settings.mirror:
        views.append((photo.flip(-1), mirrored_camera(camera.float())))
    targets = torch.stack([t.reshape(3, -1).T for t, _ in views])  # (V, M, 3)
    origins, dirs = rays_from_cameras(torch.stack([c for _, c in views]), r)
    start = planes.detach().float()
    # The prior's unit: each channel's spread over the encoder's planes, so that weight 1 means "a
    # change of one standard deviation everywhere costs as much as an L1 photo error of 1".
    spread = start.std(dim=(-2, -1), keepdim=True).clamp_min(1e-6)
    x = start.clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=settings.lr)
    gen = torch.Generator().manual_seed(settings.seed)
    n = min(settings.rays_per_step, r * r)
    rs = settings.render_settings(r)
    for _ in range(settings.steps):
        # Each view gets its own random rays; the steps' cost is split between the views.
        idx = torch.stack([torch.randperm(r * r, generator=gen)[: max(1, n // len(views))] for _ in views])
        pick = idx[..., None].expand(-1, -1, 3)
        rgb = render_rgb(x[None], decoder, origins.gather(1, pick), dirs.gather(1, pick), bounds, rs)
        fit = (rgb - targets.gather(1, pick)).abs().mean()
        prior = ((x - start) / spread).square().mean()
        loss = fit + settings.prior_weight * prior
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if on_step is not None:
            on_step()
    return x.detach()


def _input_view_psnr(
    planes: Tensor,
    decoder: tuple[Tensor, ...],
    bounds: SceneBounds,
    camera: Tensor,
    target: Tensor,
    settings: RefineSettings,
) -> float:
    r = settings.resolution
    o, d = rays_from_cameras(camera[None], r)
    with torch.no_grad():
        rgb = render_rgb(planes[None], decoder, o, d, bounds, settings.render_settings(r))[0]
    return psnr_db(rgb, target.reshape(3, -1).T)


def refine(
    triplane: TriplaneData,
    image: np.ndarray,
    settings: RefineSettings | None = None,
    *,
    pose: tuple[float, float] | None = None,
    start_camera: np.ndarray | None = None,
    on_step: Callable[[], Any] | None = None,
) -> RefineResult:
    """Fit ``triplane`` (the encoder's output) to ``image``, the photo it was lifted from: (3, S, S)
    float in [-1, 1] (``lp3d.photo.to_encoder_input`` of the crop) or (S, S, 3) uint8 (the crop).
    ``pose`` ``(yaw, pitch)`` in degrees, when known, is used as it is; else the camera is found
    (:func:`lp3d.lift.pose.find_camera`), or fitted from ``start_camera`` (25,) when given (a video's
    previous frame: no grid search). ``on_step`` is called after every pose and plane step
    (``settings.total_steps(pose is not None)`` calls: a progress bar). Raises ValueError for a bad
    image or settings."""
    settings = settings if settings is not None else RefineSettings()
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[-1] == 3 and img.dtype == np.uint8:
        img = img.transpose(2, 0, 1).astype(np.float32) / 127.5 - 1.0
    t0 = time.perf_counter()
    planes = torch.from_numpy(np.asarray(triplane.planes, np.float32))
    decoder = tuple(
        torch.from_numpy(np.asarray(getattr(triplane, k), np.float32)) for k in ("w0", "b0", "w1", "b1")
    )
    bounds = triplane.bounds
    target = photo_target(img, settings.resolution)  # checks the image before any work
    if pose is not None:
        camera = camera_at(*pose)
    elif start_camera is not None:
        start, batched = validate_camera(start_camera)
        if batched:
            raise ValueError(f"start_camera must be one camera (25,), got shape {np.shape(start_camera)}")
        camera = fit_pose(
            planes, decoder, bounds, img, torch.from_numpy(start[0]).float(), settings, on_step=on_step
        )
    else:
        camera = find_camera(planes, decoder, bounds, img, settings, on_step=on_step)
    before = _input_view_psnr(planes, decoder, bounds, camera, target, settings)
    refined = refine_planes(planes, decoder, bounds, img, camera, settings, on_step=on_step)
    after = _input_view_psnr(refined, decoder, bounds, camera, target, settings)
    out_planes = refined.numpy().astype(triplane.planes.dtype)
    source = (triplane.source or "lp3d") + f"; refined {settings.steps} steps"
    label = camera.double().numpy()
    # The occupancy grid bounds the old planes' density, not the refined ones': it is dropped.
    result = dataclasses.replace(
        triplane, planes=out_planes, camera=label, source=source[:200], occupancy=None
    )
    angles = camera_summary(label)
    return RefineResult(
        result, label, angles["yaw_deg"], angles["pitch_deg"], before, after, time.perf_counter() - t0
    )
