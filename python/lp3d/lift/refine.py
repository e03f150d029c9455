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

With the package's super-resolution network (:func:`superres_module`), the last
``superres_share`` of the steps swap the photo terms' raw rays for the final image: the whole
feature image of each view (photo and mirror) rendered and super-resolved, against the photo at the
network's output side. A raw fit at 64² leaves the face as blurred as its rays; the network then
paints the stylised detail it learnt on the teacher's heads over it. Fitting what the network makes
of the planes puts the photo's detail where `lp3d render` shows it (``docs/photos-and-video.md``
has what it buys in likeness).

Only the planes change: the decoder, scene bounds and super-resolution network are the model
package's, so the refined head renders in every tool that renders the package's heads.

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

from lp3d.lift.model_package import ModelPackage, verify_superres_file
from lp3d.lift.pose import (
    camera_at,
    find_camera,
    fit_pose,
    mirrored_camera,
    moved_camera,
    photo_target,
    render_rgb,
)
from lp3d.lift.refine_settings import RefineSettings
from lp3d.render.camera import camera_summary, validate_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.settings import SceneBounds
from lp3d.render.torch_stages import rays_from_cameras
from lp3d.render.torch_twin import render_rays
from lp3d.render.triplane import TriplaneData

__all__ = ["RefineResult", "RefineSettings", "refine", "refine_planes", "superres_module"]


def superres_module(package: ModelPackage) -> torch.nn.Module | None:
    """The package's super-resolution network as a torch module (gradients through it, weights
    frozen), read from its checked ONNX file; None for a package without one. Raises
    ModelPackageError for a missing or altered file, ValueError for a graph of another shape."""
    if package.superres is None:
        return None
    from lp3d.nets.superres_onnx import read_superres_onnx

    verify_superres_file(package.superres)
    return read_superres_onnx(package.superres.path)


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
    superres: torch.nn.Module | None = None,
    on_step: Callable[[], Any] | None = None,
) -> tuple[Tensor, Tensor]:
    """``planes`` (3, 32, T, T) float32 fitted to ``image`` (3, S, S) seen from ``camera`` (25,) by
    :class:`RefineSettings` (module docstring); with ``superres`` (the package's network as a torch
    module, :func:`superres_module`) the last ``settings.superres_share`` of the steps fit the
    super-resolved image. With ``settings.fit_camera`` the raw steps move the camera too
    (:func:`~lp3d.lift.pose.moved_camera`, the same six numbers as :func:`~lp3d.lift.pose.fit_pose`).
    Returns new planes and the camera they were fitted at (25,) float32; the inputs untouched."""
    start_camera = camera.detach().float()
    delta = torch.zeros(6, requires_grad=settings.fit_camera)

    def views() -> list[Tensor]:
        """The photo's camera (moved by ``delta``) and, with ``mirror``, its mirror image."""
        cam = moved_camera(start_camera, delta) if settings.fit_camera else start_camera
        return [cam] + ([mirrored_camera(cam)] if settings.mirror else [])

    n_views = 2 if settings.mirror else 1

    def photos(side: int) -> Tensor:
        """The photo (and its mirror image) at ``side``², (V, 3, side, side)."""
        photo = photo_target(image, side)
        return torch.stack([photo, photo.flip(-1)][:n_views])

    r = settings.resolution
    targets = photos(r).flatten(2).transpose(1, 2)  # (V, M, 3)
    origins, dirs = rays_from_cameras(torch.stack(views()), r)
    start = planes.detach().float()
    # The prior's unit: each channel's spread over the encoder's planes, so that weight 1 means "a
    # change of one standard deviation everywhere costs as much as an L1 photo error of 1".
    spread = start.std(dim=(-2, -1), keepdim=True).clamp_min(1e-6)
    x = start.clone().requires_grad_(True)
    groups = [{"params": [x], "lr": settings.lr}]
    if settings.fit_camera:
        groups.append({"params": [delta], "lr": settings.pose_lr})
    opt = torch.optim.Adam(groups)

    def step(fit: Tensor) -> None:
        prior = ((x - start) / spread).square().mean()
        loss = fit + settings.prior_weight * prior
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if on_step is not None:
            on_step()

    gen = torch.Generator().manual_seed(settings.seed)
    n = min(settings.rays_per_step, r * r)
    rs = settings.render_settings(r)
    sr_steps = settings.superres_steps(superres is not None)
    for _ in range(settings.steps - sr_steps):
        if settings.fit_camera:
            origins, dirs = rays_from_cameras(torch.stack(views()), r)
        # Each view gets its own random rays; the steps' cost is split between the views.
        idx = torch.stack(
            [torch.randperm(r * r, generator=gen)[: max(1, n // n_views)] for _ in range(n_views)]
        )
        pick = idx[..., None].expand(-1, -1, 3)
        rgb = render_rgb(x[None], decoder, origins.gather(1, pick), dirs.gather(1, pick), bounds, rs)
        step((rgb - targets.gather(1, pick)).abs().mean())
    delta = delta.detach()  # the super-resolved steps fit the planes at the camera found so far

    if superres is not None and sr_steps > 0:
        # The whole feature image of every view through the network: what `lp3d render` will show.
        side_in, side_out = superres.config.input_resolution, superres.config.output_resolution
        sr_targets = photos(side_out)
        o, d = rays_from_cameras(torch.stack(views()), side_in)
        srs = settings.render_settings(side_in, settings.superres_samples)
        for group in opt.param_groups[:1]:
            group["lr"] = settings.superres_lr
        for _ in range(sr_steps):
            out = render_rays(x[None], *decoder, o, d, bounds=bounds, settings=srs, clamp=False)
            features = out["features"].transpose(1, 2).reshape(n_views, -1, side_in, side_in)
            step((superres(features) - sr_targets).abs().mean())
    with torch.no_grad():
        return x.detach(), views()[0].detach()


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
    camera: np.ndarray | None = None,
    start_camera: np.ndarray | None = None,
    superres: torch.nn.Module | None = None,
    on_step: Callable[[], Any] | None = None,
) -> RefineResult:
    """Fit ``triplane`` (the encoder's output) to ``image``, the photo it was lifted from: (3, S, S)
    float in [-1, 1] (``lp3d.photo.to_encoder_input`` of the crop) or (S, S, 3) uint8 (the crop).
    ``pose`` ``(yaw, pitch)`` in degrees, or a whole ``camera`` label (25,), when known, is used as it
    is (then moved only with ``settings.fit_camera``); else the camera is found
    (:func:`lp3d.lift.pose.find_camera`), or fitted from ``start_camera`` (25,) when given (a video's
    previous frame: no grid search). ``superres``: the package's SR network as a torch module, for the
    super-resolved fit (:func:`refine_planes`). ``on_step`` is called after every pose and plane step
    (``settings.total_steps(pose is not None)`` calls: a progress bar). Raises
    ValueError for a bad image or settings."""
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
    if pose is not None and camera is not None:
        raise ValueError("give pose or camera, not both")
    if camera is not None:
        label, batched = validate_camera(camera)
        if batched:
            raise ValueError(f"camera must be one camera (25,), got shape {np.shape(camera)}")
        camera = torch.from_numpy(label[0]).float()
    elif pose is not None:
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
    refined, camera = refine_planes(
        planes, decoder, bounds, img, camera, settings, superres=superres, on_step=on_step
    )
    after = _input_view_psnr(refined, decoder, bounds, camera, target, settings)
    out_planes = refined.numpy().astype(triplane.planes.dtype)
    sr_steps = settings.superres_steps(superres is not None)
    how = f" ({sr_steps} super-resolved)" if sr_steps else ""
    source = (triplane.source or "lp3d") + f"; refined {settings.steps} steps{how}"
    label = camera.double().numpy()
    # The occupancy grid bounds the old planes' density, not the refined ones': it is dropped.
    result = dataclasses.replace(
        triplane, planes=out_planes, camera=label, source=source[:200], occupancy=None
    )
    angles = camera_summary(label)
    return RefineResult(
        result, label, angles["yaw_deg"], angles["pitch_deg"], before, after, time.perf_counter() - t0
    )
