"""The torch twin's stages, one function per stage of ``docs/eg3d-rendering.md``, with the float64
reference's names, arguments and quantities (``t`` depths, ``sigma_raw`` raw densities, ``feat``
features): ``rays_from_cameras`` → ``sample_stratified`` → ``sample_triplane`` → ``decode`` →
``march`` (coarse) → ``sample_importance`` / ``sample_pdf`` → ``sample_triplane`` → ``decode`` →
``unify_samples`` → ``march`` → ``clamp_depth``. :mod:`lp3d.render.torch_twin` runs them
(``render_rays``) and is the module to import; see its docstring for shapes and for where the twin
knowingly differs from EG3D's code.

May import: torch and :mod:`lp3d.render` (settings, triplane axes).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from lp3d.render.settings import (
    DENSITY_SHIFT,
    PDF_EPS,
    PDF_WEIGHT_FLOOR,
    SIGMOID_MARGIN,
    TRANSMITTANCE_EPS,
)
from lp3d.render.triplane import PLANE_AXES

__all__ = [
    "MarchResult",
    "clamp_depth",
    "decode",
    "evaluate",
    "march",
    "rays_from_cameras",
    "sample_importance",
    "sample_pdf",
    "sample_stratified",
    "sample_triplane",
    "unify_samples",
]


def rays_from_cameras(cameras: Tensor, resolution: int) -> tuple[Tensor, Tensor]:
    """Rays through the pixel centres of an ``R x R`` grid, as EG3D's RaySampler builds them.

    Args:
        cameras: (B, 25) EG3D labels: cam2world 4x4 row-major (OpenCV axes), then the 3x3 intrinsics
            normalised by image size.
        resolution: R, rays per side. Ray ``m = row * R + col``, row 0 at the top.

    Returns:
        ``(ray_origins, ray_directions)``, each (B, R*R, 3); directions have unit length, so depths
        along them are Euclidean distances from the camera centre.
    """
    n_cams = cameras.shape[0]
    cam2world = cameras[:, :16].reshape(n_cams, 4, 4)
    intrinsics = cameras[:, 16:25].reshape(n_cams, 3, 3)
    fx, fy = intrinsics[:, 0, 0, None], intrinsics[:, 1, 1, None]
    cx, cy = intrinsics[:, 0, 2, None], intrinsics[:, 1, 2, None]
    sk = intrinsics[:, 0, 1, None]

    # EG3D: arange * (1/R) + 0.5/R, i.e. normalised pixel centres.
    steps = torch.arange(resolution, dtype=cameras.dtype, device=cameras.device) * (1.0 / resolution)
    steps = steps + 0.5 / resolution
    y, x = torch.meshgrid(steps, steps, indexing="ij")
    x, y = x.reshape(1, -1), y.reshape(1, -1)

    x_lift = (x - cx + cy * sk / fy - sk * y / fy) / fx
    y_lift = (y - cy) / fy
    ones = torch.ones_like(x_lift)
    cam_rel_points = torch.stack((x_lift, y_lift, ones, ones), dim=-1)  # (B, M, 4)
    world_points = (cam_rel_points @ cam2world.transpose(1, 2))[..., :3]
    ray_origins = cam2world[:, None, :3, 3].expand_as(world_points)
    ray_directions = F.normalize(world_points - ray_origins, dim=-1)
    return ray_origins, ray_directions


def sample_stratified(
    n_rays: int | tuple[int, ...],
    *,
    depth_resolution: int,
    ray_start: float,
    ray_end: float,
    jitter: Tensor | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Coarse depths t (..., S): ``linspace(ray_start, ray_end, S) + U * (ray_end - ray_start) / (S - 1)``.

    Args:
        n_rays: number of rays, or the leading shape of the ray axes (e.g. ``(B, M)``).
        depth_resolution: S, coarse samples per ray.
        ray_start, ray_end: depth range of the linspace, the same for every ray.
        jitter: U (..., S) in [0, 1) (EG3D's ``rand_like``), or None for no jitter. When given, the
            result takes its dtype and device.
        dtype, device: of the result when ``jitter`` is None.

    Returns:
        t: (..., S), ascending; jittered samples may reach one step past ray_end.
    """
    lead = (n_rays,) if isinstance(n_rays, int) else tuple(n_rays)
    if jitter is not None:
        dtype, device = jitter.dtype, jitter.device
    # torch's CPU linspace is the bit-exact recipe (docs/eg3d-rendering.md §7): build it there on any device.
    lin = torch.linspace(ray_start, ray_end, depth_resolution, dtype=dtype).to(device)
    t = lin.expand(*lead, depth_resolution)
    if jitter is not None:
        if tuple(jitter.shape) != tuple(t.shape):
            raise ValueError(f"jitter must have shape {tuple(t.shape)}, got {tuple(jitter.shape)}")
        # The jitter step is the Python-float (float64) step, as in EG3D, not the linspace's own.
        t = t + jitter * ((ray_end - ray_start) / (depth_resolution - 1))
    return t


def sample_pdf(bins: Tensor, weights: Tensor, u: Tensor, *, eps: float = PDF_EPS) -> Tensor:
    """Inverse-CDF samples (n, N) from bin edges (n, nb) and weights (n, nw), nw <= nb - 1 (§9.4).

    EG3D's ``sample_pdf``: ``pdf = (w + eps) / sum``, ``cdf = [0, cumsum(pdf)]`` (nw + 1 entries),
    ``idx = searchsorted(cdf, u, right=True)``, ``below = max(idx - 1, 0)``, ``above = min(idx, nw)``,
    ``denom = cdf[above] - cdf[below]`` (1 where < eps), ``t = bins[below] + (u - cdf[below]) / denom *
    (bins[above] - bins[below])``. Only edges 0..nw are used (EG3D passes nb = nw + 2).

    Args:
        bins: (n, nb); weights: (n, nw) non-negative; u: (n, N) in [0, 1].

    Returns:
        (n, N) depths, not sorted unless ``u`` is, and not clamped.
    """
    n_bins = weights.shape[-1]
    weights = weights + eps
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cumsum(pdf, dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], dim=-1).contiguous()  # (n, nw + 1)
    u = u.contiguous()

    inds = torch.searchsorted(cdf, u, right=True)
    below = torch.clamp_min(inds - 1, 0)
    above = torch.clamp_max(inds, n_bins)
    cdf_below, cdf_above = cdf.gather(1, below), cdf.gather(1, above)
    bins_below, bins_above = bins.gather(1, below), bins.gather(1, above)

    denom = cdf_above - cdf_below
    denom = torch.where(denom < eps, torch.ones_like(denom), denom)
    return bins_below + (u - cdf_below) / denom * (bins_above - bins_below)


def sample_importance(
    t_coarse: Tensor, coarse_weights: Tensor, n_importance: int, u: Tensor | None = None
) -> Tensor:
    """Fine depths (..., N) drawn from the smoothed coarse weights (EG3D's ``sample_importance``, §9).

    The S-1 coarse weights are max-pooled (kernel 2, stride 1, padding 1), average-pooled (kernel 2,
    stride 1) and get +0.01; their inner S-3 values weight the bins between coarse midpoints. As in
    EG3D the result carries no gradient.

    Args:
        t_coarse: (..., S) ascending coarse depths, S >= 4.
        coarse_weights: (..., S-1) weights of the coarse ``march``.
        n_importance: N.
        u: (..., N) in [0, 1] (the jittered mode's sorted draw), or None for EG3D's ``det=True`` draw
            ``linspace(0, 1, N)`` (including 1).

    Returns:
        t_fine: (..., N), detached.
    """
    with torch.no_grad():
        lead, n_coarse = t_coarse.shape[:-1], t_coarse.shape[-1]
        t = t_coarse.reshape(-1, n_coarse)
        w = coarse_weights.reshape(-1, 1, n_coarse - 1)
        w = F.max_pool1d(w, 2, 1, padding=1)
        w = F.avg_pool1d(w, 2, 1).squeeze(1) + PDF_WEIGHT_FLOOR
        mids = 0.5 * (t[:, :-1] + t[:, 1:])
        if u is None:
            flat_u = torch.linspace(0, 1, n_importance, dtype=t.dtype).to(t.device).expand(t.shape[0], -1)
        else:
            flat_u = u.reshape(-1, n_importance)
        t_fine = sample_pdf(mids, w[:, 1 : n_coarse - 2], flat_u)
    return t_fine.reshape(*lead, n_importance)


def sample_triplane(planes: Tensor, points: Tensor, *, box_warp: float = 1.0) -> Tensor:
    """Mean of the three planes' bilinear features at world points (EG3D's ``sample_from_planes``, §2-§4).

    Points are scaled by ``2 / box_warp`` and plane p reads the world axes ``PLANE_AXES[p]`` as (u, v)
    (EG3D's (x,y), (x,z), (z,x) quirk), with ``grid_sample(bilinear, zeros, align_corners=False)``.
    Points outside the box are not masked: their taps read zeros, as in EG3D.

    Args:
        planes: (P, 3, C, H, W).
        points: (P, K, 3) world points; point k of triplane p is looked up in ``planes[p]``.
        box_warp: side of the world cube the triplane spans.

    Returns:
        features: (P, K, C), averaged over the three planes.
    """
    n_tri, n_planes, channels, height, width = planes.shape
    n_points = points.shape[1]
    q = points * (2.0 / box_warp)
    # (P, 3, K, 2): each plane's (u, v) world axes. Basic indexing, not ``q[:, :, tensor]``: that one's
    # backward is index_put_(accumulate=True), which on the CPU sums the two planes that share an axis
    # in thread order, so the same fit (lp3d encode --refine) differed from run to run.
    grid = torch.stack([torch.stack((q[..., u], q[..., v]), dim=-1) for u, v in PLANE_AXES], dim=1)
    grid = grid.reshape(n_tri * n_planes, 1, n_points, 2)
    sampled = F.grid_sample(
        planes.reshape(n_tri * n_planes, channels, height, width),
        grid,
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )  # (P*3, C, 1, K)
    return sampled.reshape(n_tri, n_planes, channels, n_points).mean(dim=1).transpose(1, 2)


def decode(features: Tensor, w0: Tensor, b0: Tensor, w1: Tensor, b1: Tensor) -> tuple[Tensor, Tensor]:
    """EG3D's OSGDecoder with effective weights: ``h = softplus(W0 f + b0)``, ``o = W1 h + b1`` (§4).

    Args:
        features: (..., 32) plane-averaged features from ``sample_triplane``.
        w0, b0, w1, b1: (64, 32), (64,), (33, 64), (33,) effective weights.

    Returns:
        ``(sigma_raw, feat)``: (...) raw densities ``o[0]`` (no activation; ``march`` applies
        softplus(x - 1)) and (..., 32) features ``sigmoid(o[1:]) * 1.002 - 0.001``.
    """
    hidden = F.softplus(F.linear(features, w0, b0))  # beta 1, threshold 20: torch.nn.Softplus defaults
    out = F.linear(hidden, w1, b1)
    feat = torch.sigmoid(out[..., 1:]) * (1 + 2 * SIGMOID_MARGIN) - SIGMOID_MARGIN
    return out[..., 0], feat


class MarchResult(NamedTuple):
    """Output of ``march``: ``features`` (..., C) already mapped ``* 2 - 1``; ``depth`` (...) before the
    batch-wide clamp (+inf where W = 0); ``weights`` (..., K-1); ``weights_sum`` W (...)."""

    features: Tensor
    depth: Tensor
    weights: Tensor
    weights_sum: Tensor


def march(t: Tensor, sigma_raw: Tensor, feat: Tensor, *, white_back: bool = False) -> MarchResult:
    """EG3D's MipRayMarcher2 over sorted depths t (..., K), raw densities (..., K), features (..., K, C).

    K samples give K-1 intervals (no infinite last interval). Per interval: midpoint colour and depth,
    ``sigma = softplus(mean of the two raw densities - 1)``, ``alpha = 1 - exp(-sigma * delta)``;
    transmittance is the exclusive cumprod of ``(1 - alpha) + 1e-10``. Depth is the weighted mean
    midpoint, +inf where W = 0 (EG3D's NaN → inf); the caller clamps it to the batch's sample range
    (``clamp_depth``).
    """
    delta = t[..., 1:] - t[..., :-1]
    feat_mid = (feat[..., :-1, :] + feat[..., 1:, :]) / 2
    t_mid = (t[..., :-1] + t[..., 1:]) / 2
    sigma = F.softplus((sigma_raw[..., :-1] + sigma_raw[..., 1:]) / 2 - DENSITY_SHIFT)
    # 1 - exp(-x), written as -expm1(-x): the same function, but accurate in float32 for the tiny x of
    # near-empty space, where 1 - exp(-x) loses most digits (and with them the depth of faint rays).
    alpha = -torch.expm1(-sigma * delta)
    shifted = torch.cat([torch.ones_like(alpha[..., :1]), 1 - alpha + TRANSMITTANCE_EPS], dim=-1)
    weights = alpha * torch.cumprod(shifted, dim=-1)[..., :-1]

    weights_sum = weights.sum(dim=-1)
    rgb = (weights.unsqueeze(-2) @ feat_mid).squeeze(-2)
    # EG3D: 0/0 = NaN → +inf. Guarding the division keeps those values and gives 0, not NaN, gradients.
    has_weight = weights_sum > 0
    safe_sum = torch.where(has_weight, weights_sum, torch.ones_like(weights_sum))
    depth = torch.where(
        has_weight, (weights * t_mid).sum(dim=-1) / safe_sum, torch.full_like(safe_sum, math.inf)
    )
    if white_back:
        rgb = rgb + (1 - weights_sum).unsqueeze(-1)
    return MarchResult(rgb * 2 - 1, depth, weights, weights_sum)


def clamp_depth(depth: Tensor, t: Tensor) -> Tensor:
    """EG3D's clamp of ``depth`` (any shape) to [min, max] of *every* sample depth ``t`` of the batch.

    Only rays with zero weight (depth +inf) are affected in practice: they get the batch's largest
    sample depth; any other depth is already a convex combination of its ray's midpoints.
    """
    bounds = t.detach()
    return torch.clamp(depth, bounds.min(), bounds.max())


def unify_samples(
    t1: Tensor, sigma_raw1: Tensor, feat1: Tensor, t2: Tensor, sigma_raw2: Tensor, feat2: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Merge two sample lists per ray and sort them by depth (EG3D's ``unify_samples``, §9.6).

    Args:
        t*: (..., K*); sigma_raw*: (..., K*); feat*: (..., K*, C).

    Returns:
        ``(t, sigma_raw, feat)`` with K = K1 + K2 samples, ascending in t. The coarse samples' values are
        reused, not recomputed.
    """
    t = torch.cat([t1, t2], dim=-1)
    sigma_raw = torch.cat([sigma_raw1, sigma_raw2], dim=-1)
    feat = torch.cat([feat1, feat2], dim=-2)
    # Stable for reproducibility; tied depths are the same point, so their order does not matter.
    t, order = torch.sort(t, dim=-1, stable=True)
    feat = feat.gather(-2, order.unsqueeze(-1).expand_as(feat))
    return t, sigma_raw.gather(-1, order), feat


def evaluate(
    planes: Tensor, w0: Tensor, b0: Tensor, w1: Tensor, b1: Tensor, points: Tensor, *, box_warp: float
) -> tuple[Tensor, Tensor]:
    """Triplane lookup and decoder at ``points`` (B, M, K, 3) → sigma_raw (B, M, K), feat (B, M, K, 32).

    ``planes`` is (P, 3, C, H, W) with P = B, or P = 1 shared by all cameras.
    """
    lead = points.shape[:3]
    flat = points.reshape(planes.shape[0], -1, 3)  # a shared triplane sees every camera's points at once
    sigma_raw, feat = decode(sample_triplane(planes, flat, box_warp=box_warp), w0, b0, w1, b1)
    return sigma_raw.reshape(lead), feat.reshape(*lead, -1)
