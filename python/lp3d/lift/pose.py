"""The camera a photo was taken from, found by fitting the lifted head to it (``lp3d encode --refine``).

A photo comes with no camera, and a refinement is only as good as its camera: fitted at a pose 10°
off, the planes learn the photo from the wrong side and the side views ghost. Two stages:

* :func:`estimate_pose`: a grid search over yaw and pitch around the training framing (the crop of
  :mod:`lp3d.photo` puts every face there), keeping the camera whose render of the encoder's head is
  closest (L1) to the photo. A grid camera has FFHQ's focal length, radius and centred principal
  point, which the photo's need not have: the best grid camera can be 15° off in yaw, because a yaw
  turn also slides the head sideways in the image and stands in for a shifted crop.
* :func:`fit_pose`: gradient descent on a small move of that camera (:func:`moved_camera`: a rotation
  about the world origin, which turns yaw, pitch and roll; a shift of the principal point; a scale of
  the focal length), the planes held fixed. With those six numbers free, yaw no longer has to
  explain a shifted or zoomed crop.

The moves compose with the camera label (``lp3d.render.camera``): nothing here redefines the look-at
convention. May import :mod:`lp3d.render`; needs torch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lp3d.lift.refine_settings import RefineSettings
from lp3d.render.camera import look_at_camera
from lp3d.render.settings import RenderSettings, SceneBounds
from lp3d.render.torch_stages import rays_from_cameras
from lp3d.render.torch_twin import render_rays

__all__ = [
    "camera_at",
    "estimate_pose",
    "find_camera",
    "fit_pose",
    "mirrored_camera",
    "moved_camera",
    "photo_target",
    "render_rgb",
]


def photo_target(image: np.ndarray | Tensor, resolution: int) -> Tensor:
    """The photo (3, S, S) float in [-1, 1] at ``resolution`` rays per side (area average), (3, R, R)."""
    x = torch.as_tensor(np.asarray(image, np.float32) if not isinstance(image, Tensor) else image)
    if x.ndim != 3 or x.shape[0] != 3 or x.shape[1] != x.shape[2] or x.shape[1] < 8:
        raise ValueError(f"image must be (3, S, S) float in [-1, 1] with S >= 8, got shape {tuple(x.shape)}")
    x = x.float()
    if not bool(torch.isfinite(x).all()):
        raise ValueError("image contains NaN/Inf")
    if x.shape[1] == resolution:
        return x
    return F.interpolate(
        x[None], size=(resolution, resolution), mode="area" if x.shape[1] > resolution else "bilinear"
    )[0]


def camera_at(yaw: float, pitch: float) -> Tensor:
    """The look-at camera label (25,) float32 at ``yaw``, ``pitch`` degrees, FFHQ's framing."""
    return torch.from_numpy(look_at_camera(yaw_deg=yaw, pitch_deg=pitch)).float()


def render_rgb(
    planes: Tensor,
    decoder: tuple[Tensor, ...],
    origins: Tensor,
    dirs: Tensor,
    bounds: SceneBounds,
    settings: RenderSettings,
) -> Tensor:
    """Raw RGB (B, M, 3) of rays (B, M, 3) through shared planes (1, 3, 32, T, T)."""
    out = render_rays(planes, *decoder, origins, dirs, bounds=bounds, settings=settings, clamp=False)
    return out["features"][..., :3]


def _rotation(axis_angle: Tensor) -> Tensor:
    """Rodrigues: the (3, 3) rotation by ``|axis_angle|`` radians about its direction; smooth at 0."""
    theta2 = axis_angle.square().sum()
    theta = torch.sqrt(theta2 + 1e-24)
    x, y, z = axis_angle.unbind()
    zero = torch.zeros_like(x)
    k = torch.stack([torch.stack([zero, -z, y]), torch.stack([z, zero, -x]), torch.stack([-y, x, zero])])
    # sin(t)/t and (1 - cos(t))/t² by their series near 0, where the division loses precision.
    small = theta < 1e-4
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta.clamp_min(1e-4).square())
    return torch.eye(3, dtype=axis_angle.dtype) + a * k + b * (k @ k)


def mirrored_camera(camera: Tensor) -> Tensor:
    """``camera`` (25,) mirrored in the world's x = 0 plane (the face's plane of symmetry): it sees the
    mirror image of what ``camera`` sees, so a photo flipped left to right is its view. The camera's
    x axis is flipped too (the frame stays right-handed) and the principal point moves to 1 - cx."""
    flip = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=camera.dtype))
    cam2world = flip @ camera[:16].reshape(4, 4) @ flip
    k = camera[16:25].reshape(3, 3).clone()
    k[0, 2] = 1.0 - k[0, 2]
    k[0, 1] = -k[0, 1]
    return torch.cat([cam2world.reshape(-1), k.reshape(-1)])


def moved_camera(camera: Tensor, delta: Tensor) -> Tensor:
    """``camera`` (25,) moved by ``delta`` (6,), differentiably in ``delta``:

    * ``delta[0:3]``: a rotation (axis-angle, radians, world axes) of the whole camera about the world
      origin, as an orbit turns it: about +y it changes the yaw, about the camera's right axis the pitch,
      about its viewing axis the roll;
    * ``delta[3:5]``: a shift of the principal point (cx, cy), in units of the image size;
    * ``delta[5]``: the log of a scale of the focal length (fx and fy alike).

    All zeros give ``camera`` back exactly."""
    cam2world = camera[:16].reshape(4, 4)
    k = camera[16:25].reshape(3, 3)
    rot = _rotation(delta[:3])
    top = torch.cat([rot @ cam2world[:3, :3], (rot @ cam2world[:3, 3])[:, None]], dim=1)
    scale = torch.exp(delta[5])
    k_new = torch.stack(
        [
            torch.stack([k[0, 0] * scale, k[0, 1], k[0, 2] + delta[3]]),
            torch.stack([k[1, 0], k[1, 1] * scale, k[1, 2] + delta[4]]),
            k[2],
        ]
    )
    return torch.cat([top.reshape(-1), cam2world[3], k_new.reshape(-1)])


def estimate_pose(
    planes: Tensor,
    decoder: tuple[Tensor, ...],
    bounds: SceneBounds,
    image: np.ndarray | Tensor,
    settings: RefineSettings,
) -> tuple[float, float]:
    """``(yaw, pitch)`` in degrees of the grid camera whose render of ``planes`` (3, 32, T, T) is
    closest (L1) to ``image`` (3, S, S) in [-1, 1]; :class:`RefineSettings` names the grid."""
    r = settings.search_resolution
    target = photo_target(image, r).reshape(3, -1).T[None]  # (1, M, 3)
    poses = [(y, p) for p in settings.search_pitches_deg for y in settings.search_yaws_deg]
    # One batched render of every grid camera through the shared planes, not one call per pose.
    o, d = rays_from_cameras(torch.stack([camera_at(y, p) for y, p in poses]), r)
    with torch.no_grad():
        rgb = render_rgb(planes[None], decoder, o, d, bounds, settings.render_settings(r))
    errors = (rgb - target).abs().mean(dim=(1, 2))
    return poses[int(torch.argmin(errors))]


def fit_pose(
    planes: Tensor,
    decoder: tuple[Tensor, ...],
    bounds: SceneBounds,
    image: np.ndarray | Tensor,
    camera: Tensor,
    settings: RefineSettings,
    *,
    on_step: Callable[[], Any] | None = None,
) -> Tensor:
    """``camera`` (25,) moved (:func:`moved_camera`) to fit the render of ``planes`` (3, 32, T, T),
    held fixed, to ``image``: ``settings.pose_steps`` Adam steps (learning rate ``pose_lr`` decayed
    to 0 on a cosine) on the L1 photo error of every ray of a ``pose_resolution``² view. Returns the
    new label (25,) float32."""
    r = settings.pose_resolution
    target = photo_target(image, r).reshape(3, -1).T[None]
    start = camera.detach().float()
    delta = torch.zeros(6, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=settings.pose_lr)
    # Adam moves every parameter by about lr a step whatever the gradient's size; the cosine decay
    # lets the last steps settle instead of circling the optimum by lr.
    n = settings.pose_steps
    decay = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.5 * (1.0 + math.cos(math.pi * i / n)))
    held = planes.detach().float()[None]
    rs = settings.render_settings(r)
    for _ in range(n):
        o, d = rays_from_cameras(moved_camera(start, delta)[None], r)
        loss = (render_rgb(held, decoder, o, d, bounds, rs) - target).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        decay.step()
        if on_step is not None:
            on_step()
    with torch.no_grad():
        return moved_camera(start, delta)


def find_camera(
    planes: Tensor,
    decoder: tuple[Tensor, ...],
    bounds: SceneBounds,
    image: np.ndarray | Tensor,
    settings: RefineSettings,
    *,
    on_step: Callable[[], Any] | None = None,
) -> Tensor:
    """The photo's camera (25,): :func:`estimate_pose` on the grid, then :func:`fit_pose` from there."""
    yaw, pitch = estimate_pose(planes, decoder, bounds, image, settings)
    return fit_pose(planes, decoder, bounds, image, camera_at(yaw, pitch), settings, on_step=on_step)
