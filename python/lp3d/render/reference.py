"""Float64 NumPy reference renderer with EG3D's exact semantics.

It states the semantics of ``docs/eg3d-rendering.md`` (section numbers below refer to it) as the
slow, obvious ground truth that the WGSL renderer and the torch twin are tested against. Functions
follow the data flow: :func:`rays_from_cameras` (camera) -> :func:`sample_stratified` (sampling) ->
:func:`sample_triplane` (triplane) -> :func:`decode` (decoder) -> :func:`march` (compositing) ->
:func:`sample_importance` / :func:`sample_pdf` (sampling) -> :func:`render_reference` (all of it).
Everything is vectorised over rays; ``...`` in shapes means any leading ray axes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from lp3d.render.camera import validate_camera
from lp3d.render.sampling_rng import coarse_jitter, sorted_importance_u
from lp3d.render.settings import (
    DENSITY_SHIFT,
    PDF_EPS,
    PDF_WEIGHT_FLOOR,
    SIGMOID_MARGIN,
    TRANSMITTANCE_EPS,
    RenderSettings,
    resolve_settings,
)
from lp3d.render.triplane import PLANE_AXES, TriplaneData

#: Rays per chunk in render_reference: bounds the (rays, samples, 32) temporaries to a few tens of MB.
_CHUNK_RAYS = 1024


# ---------------------------------------------------------------------------------------------- camera


def rays_from_cameras(cameras: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions, ``(B, R*R, 3)`` each, for cameras (B, 25) (§6).

    Pixel ``m = row * R + col``, row 0 at the top; pixel centres at ``(k + 0.5) / R`` in normalised
    image coordinates. Depth along these unit directions is Euclidean distance from the camera centre.
    """
    cams, _ = validate_camera(cameras)
    R = int(resolution)
    c2w = cams[:, :16].reshape(-1, 4, 4)
    K = cams[:, 16:].reshape(-1, 3, 3)
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    cx, cy, sk = K[:, 0, 2, None], K[:, 1, 2, None], K[:, 0, 1, None]
    centres = np.arange(R) * (1.0 / R) + 0.5 / R
    y, x = (a.reshape(1, -1) for a in np.meshgrid(centres, centres, indexing="ij"))  # (1, R*R), m = row*R+col
    x_cam = (x - cx + cy * sk / fy - sk * y / fy) / fx
    y_cam = (y - cy) / fy
    ones = np.ones_like(x_cam)
    p_cam = np.stack([x_cam, y_cam, ones, ones], axis=-1)  # (B, R*R, 4) homogeneous, z = 1
    p_world = np.einsum("bij,bmj->bmi", c2w, p_cam)[..., :3]
    origins = np.broadcast_to(c2w[:, None, :3, 3], p_world.shape).copy()
    dirs = p_world - origins
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return origins, dirs


# -------------------------------------------------------------------------------------------- sampling


def sample_stratified(
    n_rays: int,
    *,
    depth_resolution: int,
    ray_start: float,
    ray_end: float,
    jitter: np.ndarray | None = None,
) -> np.ndarray:
    """Coarse depths ``t`` (n_rays, S) (§7): ``linspace(ray_start, ray_end, S) + U * (end - start)/(S-1)``.

    ``jitter`` is ``U`` (n_rays, S) in [0, 1), or None for the deterministic U = 0. The same linspace
    serves every ray (no ray/box intersection), so jittered samples may reach one step past ray_end.
    """
    S = int(depth_resolution)
    lin = np.linspace(float(ray_start), float(ray_end), S)
    t = np.broadcast_to(lin, (int(n_rays), S)).copy()
    if jitter is not None:
        U = np.asarray(jitter, dtype=np.float64)
        if U.shape != t.shape:
            raise ValueError(f"jitter must have shape {t.shape}, got {U.shape}")
        t += U * ((float(ray_end) - float(ray_start)) / (S - 1))
    return t


def sample_pdf(bins: np.ndarray, weights: np.ndarray, u: np.ndarray, *, eps: float = PDF_EPS) -> np.ndarray:
    """Inverse-CDF samples (..., N) from bin edges (..., nb) and weights (..., nw), nw <= nb - 1 (§9.4).

    EG3D's ``sample_pdf``: ``pdf = (w + eps) / sum``, ``cdf = [0, cumsum(pdf)]`` (nw + 1 entries),
    ``idx = searchsorted(cdf, u, right=True)``, ``below = max(idx - 1, 0)``, ``above = min(idx, nw)``,
    ``denom = cdf[above] - cdf[below]`` (set to 1 where < eps), and
    ``t = bins[below] + (u - cdf[below]) / denom * (bins[above] - bins[below])``. Only edges
    0..nw are ever used (EG3D passes nb = nw + 2, leaving the last edge unused).
    """
    w = np.asarray(weights, dtype=np.float64) + eps
    nw = w.shape[-1]
    if bins.shape[-1] < nw + 1:
        raise ValueError(f"need at least {nw + 1} bin edges for {nw} weights, got {bins.shape[-1]}")
    pdf = w / w.sum(axis=-1, keepdims=True)
    cdf = np.concatenate([np.zeros_like(pdf[..., :1]), np.cumsum(pdf, axis=-1)], axis=-1)
    u = np.asarray(u, dtype=np.float64)
    # searchsorted(right=True) on a non-decreasing cdf = number of entries <= u, vectorised over rays.
    idx = np.sum(cdf[..., None, :] <= u[..., :, None], axis=-1)
    below = np.maximum(idx - 1, 0)
    above = np.minimum(idx, nw)
    cdf_b = np.take_along_axis(cdf, below, axis=-1)
    cdf_a = np.take_along_axis(cdf, above, axis=-1)
    bins_b = np.take_along_axis(bins, below, axis=-1)
    bins_a = np.take_along_axis(bins, above, axis=-1)
    denom = cdf_a - cdf_b
    denom = np.where(denom < eps, 1.0, denom)
    return bins_b + (u - cdf_b) / denom * (bins_a - bins_b)


def sample_importance(
    t_coarse: np.ndarray, coarse_weights: np.ndarray, n_importance: int, u: np.ndarray | None = None
) -> np.ndarray:
    """Fine depths (..., N) from coarse depths (..., S) and coarse march weights (..., S-1) (§9.2-9.4).

    Weights are smoothed as EG3D does (max_pool1d k2 s1 p1, avg_pool1d k2 s1, + 0.01) and
    ``a[1:S-2]`` (S-3 values) is the pdf over the coarse midpoints. ``u`` (..., N) in [0, 1]; None
    means EG3D's ``det=True`` draw ``linspace(0, 1, N)`` (including 1). Results are not sorted
    unless ``u`` is.
    """
    t = np.asarray(t_coarse, dtype=np.float64)
    w = np.asarray(coarse_weights, dtype=np.float64)
    S = t.shape[-1]
    if S < 4 or w.shape != (*t.shape[:-1], S - 1):
        raise ValueError(f"need S >= 4 coarse depths and S-1 weights, got {t.shape} and {w.shape}")
    # max_pool1d(kernel 2, stride 1, padding 1) with -inf padding: m_j = max(w_{j-1}, w_j), S values.
    m = np.concatenate([w[..., :1], np.maximum(w[..., :-1], w[..., 1:]), w[..., -1:]], axis=-1)
    a = 0.5 * (m[..., :-1] + m[..., 1:]) + PDF_WEIGHT_FLOOR  # avg_pool1d(kernel 2, stride 1): S-1 values
    mids = 0.5 * (t[..., :-1] + t[..., 1:])
    if u is None:
        u = np.broadcast_to(np.linspace(0.0, 1.0, int(n_importance)), (*t.shape[:-1], int(n_importance)))
    else:
        u = np.asarray(u, dtype=np.float64)
        if u.shape != (*t.shape[:-1], int(n_importance)):
            raise ValueError(f"u must have shape {(*t.shape[:-1], int(n_importance))}, got {u.shape}")
    return sample_pdf(mids, a[..., 1 : S - 2], u)


# -------------------------------------------------------------------------------------------- triplane


def grid_sample_bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``grid_sample(bilinear, zeros, align_corners=False)`` of image (C, H, W) at (u, v) -> (..., C) (§3).

    ``u`` in [-1, 1] spans W (columns), ``v`` spans H (rows). Zero padding is per tap, so values fade
    to 0 between the outermost texel centre (±(1 - 1/W)) and ±(1 + 1/W), and are exactly 0 beyond.
    """
    img = np.moveaxis(np.asarray(image, dtype=np.float64), 0, -1)  # (H, W, C): gathers give (..., C)
    H, W = img.shape[:2]
    # Clipping to [-2, size + 1] changes nothing (both taps are outside there) and keeps ints small.
    ix = np.clip(((np.asarray(u, dtype=np.float64) + 1.0) * W - 1.0) / 2.0, -2.0, W + 1.0)
    iy = np.clip(((np.asarray(v, dtype=np.float64) + 1.0) * H - 1.0) / 2.0, -2.0, H + 1.0)
    x0 = np.floor(ix).astype(np.int64)
    y0 = np.floor(iy).astype(np.int64)
    fx = ix - x0
    fy = iy - y0
    texels = img.reshape(H * W, -1)
    out = np.zeros((*ix.shape, texels.shape[1]))
    for dx, dy, wgt in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
        flat = np.clip(yi, 0, H - 1) * W + np.clip(xi, 0, W - 1)
        out += (wgt * inside)[..., None] * np.take(texels, flat, axis=0)
    return out


def sample_triplane(planes: np.ndarray, points: np.ndarray, *, box_warp: float = 1.0) -> np.ndarray:
    """Mean of the three planes' bilinear features at world points (..., 3) -> (..., C) (§2-§4).

    Points are scaled by ``2 / box_warp`` (no centre offset, no masking outside the box) and plane p
    reads the world axes ``PLANE_AXES[p]`` as (u, v), EG3D's quirk included.
    """
    q = np.asarray(points, dtype=np.float64) * (2.0 / float(box_warp))
    planes = np.asarray(planes)
    total = sum(grid_sample_bilinear(planes[p], q[..., a], q[..., b]) for p, (a, b) in enumerate(PLANE_AXES))
    return total / len(PLANE_AXES)


# --------------------------------------------------------------------------------------------- decoder


def softplus(x: np.ndarray) -> np.ndarray:
    """torch ``Softplus()`` (beta 1, threshold 20): x where x > 20, else log(1 + exp(x))."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x > 20.0, x, np.log1p(np.exp(np.minimum(x, 20.0))))


def sigmoid(x: np.ndarray) -> np.ndarray:
    """``1 / (1 + exp(-x))``; exp overflow for very negative x correctly gives 0."""
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def decode(
    features: np.ndarray, w0: np.ndarray, b0: np.ndarray, w1: np.ndarray, b1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """OSGDecoder with effective weights: features (..., 32) -> ``(sigma_raw (...), feat (..., 32))`` (§4).

    ``h = softplus(W0 f + b0)``, ``o = W1 h + b1``; ``sigma_raw = o[0]`` (no activation) and
    ``feat = sigmoid(o[1:]) * 1.002 - 0.001``.
    """
    f = np.asarray(features, dtype=np.float64)
    h = softplus(f @ np.asarray(w0, np.float64).T + np.asarray(b0, np.float64))
    o = h @ np.asarray(w1, np.float64).T + np.asarray(b1, np.float64)
    return o[..., 0], sigmoid(o[..., 1:]) * (1.0 + 2 * SIGMOID_MARGIN) - SIGMOID_MARGIN


# ---------------------------------------------------------------------------------------------- march


class MarchResult(NamedTuple):
    """Output of :func:`march`. ``features`` (..., C) already mapped ``* 2 - 1``; ``depth`` (...) before
    the batch-wide clamp (+inf where W = 0); ``weights`` (..., K-1); ``weights_sum`` W (...)."""

    features: np.ndarray
    depth: np.ndarray
    weights: np.ndarray
    weights_sum: np.ndarray


def interval_alpha(sigma_raw_a: np.ndarray, sigma_raw_b: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The opacity of an interval of length ``delta`` between samples of raw densities a and b:
    ``1 - exp(-softplus((a + b) / 2 - 1) delta)``."""
    sigma = softplus(0.5 * (sigma_raw_a + sigma_raw_b) - DENSITY_SHIFT)
    return -np.expm1(-sigma * delta)  # exact for tiny sigma*delta, where 1 - exp(-x) rounds to 0


def march(t: np.ndarray, sigma_raw: np.ndarray, feat: np.ndarray, *, white_back: bool = False) -> MarchResult:
    """MipRayMarcher2 over sorted depths t (..., K), raw densities (..., K), features (..., K, C) (§8).

    K samples give K-1 intervals (no infinite last delta). Per interval: midpoint colour and depth,
    ``sigma = softplus(mean of the two raw densities - 1)``, ``alpha = 1 - exp(-sigma * delta)``;
    transmittance is the exclusive cumprod of ``(1 - alpha) + 1e-10``. Depth is the weighted mean
    midpoint, with NaN (W = 0) replaced by +inf; the caller clamps it to the batch's sample range.
    """
    t = np.asarray(t, dtype=np.float64)
    s = np.asarray(sigma_raw, dtype=np.float64)
    c = np.asarray(feat, dtype=np.float64)
    delta = t[..., 1:] - t[..., :-1]
    c_mid = 0.5 * (c[..., :-1, :] + c[..., 1:, :])
    t_mid = 0.5 * (t[..., :-1] + t[..., 1:])
    alpha = interval_alpha(s[..., :-1], s[..., 1:], delta)
    shifted = np.concatenate([np.ones_like(alpha[..., :1]), (1.0 - alpha) + TRANSMITTANCE_EPS], axis=-1)
    T = np.cumprod(shifted, axis=-1)[..., :-1]
    weights = alpha * T
    W = weights.sum(axis=-1)
    rgb = np.einsum("...k,...kc->...c", weights, c_mid)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = (weights * t_mid).sum(axis=-1) / W
    depth = np.where(np.isnan(depth), np.inf, depth)
    if white_back:
        rgb = rgb + (1.0 - W)[..., None]
    return MarchResult(rgb * 2.0 - 1.0, depth, weights, W)


# ------------------------------------------------------------------------------------------- renderer


def _as_triplane(triplane: Any) -> TriplaneData:
    """A validated TriplaneData from any object with the triplane attributes (e.g. lp3d_render.Triplane)."""
    if isinstance(triplane, TriplaneData):
        triplane.validate()
        return triplane
    try:
        fields = {k: getattr(triplane, k) for k in ("planes", "w0", "b0", "w1", "b1")}
        scalars = {k: getattr(triplane, k) for k in ("box_warp", "ray_start", "ray_end")}
    except AttributeError as e:
        raise TypeError(
            f"triplane must have planes, w0, b0, w1, b1, box_warp, ray_start, ray_end: {e}"
        ) from None
    return TriplaneData(**{k: np.asarray(v) for k, v in fields.items()}, **scalars)


def _evaluate(tri: TriplaneData, planes: np.ndarray, o: np.ndarray, d: np.ndarray, t: np.ndarray):
    """Raw densities (n, K) and features (n, K, 32) at depths t (n, K) along rays o + t d (n, 3)."""
    points = o[:, None, :] + t[..., None] * d[:, None, :]
    return decode(sample_triplane(planes, points, box_warp=tri.box_warp), tri.w0, tri.b0, tri.w1, tri.b1)


def render_reference(
    triplane: Any, camera: np.ndarray, settings: RenderSettings | None = None, **overrides: Any
) -> dict[str, np.ndarray]:
    """Render a triplane with EG3D's renderer semantics in float64.

    ``camera`` (25,) or (B, 25); ``settings`` a :class:`~lp3d.render.settings.RenderSettings` (default
    ``RenderSettings()``, exact: no skips), which keyword arguments override (``resolution=64``; a
    :class:`~lp3d.render.settings.SceneBounds` field overrides the triplane's bounds). Returns float64
    ``features`` (32, R, R) (in ~[-1, 1]), ``rgb`` (3, R, R) (= ``features[:3]``), ``depth`` (R, R) and
    ``weights_sum`` (R, R), each with a leading B axis when ``camera`` is 2-D. Coarse pass (S samples),
    then, unless ``depth_resolution_importance`` is 0, an importance pass (N samples) and one march over
    the merged sorted S + N samples. Depth: NaN (no
    opacity) -> +inf, then clamped to [min, max] of every sample depth in the whole batch (EG3D).
    ``deterministic``: no jitter and ``u = linspace(0, 1, N)``; otherwise ``docs/sampling-rng.md`` with
    ``seed`` and global ray index ``b * R * R + row * R + col``.
    """
    tri = _as_triplane(triplane)
    settings, bounds = resolve_settings(settings, overrides, tri.bounds)
    settings.require_exact("the float64 reference")
    if bounds != tri.bounds:  # rendered with other bounds than the triplane's own
        tri = dataclasses.replace(tri, **dataclasses.asdict(bounds))
    planes = tri.planes.astype(np.float64)
    return render_with(tri, camera, settings, lambda o, d, t: _evaluate(tri, planes, o, d, t))


#: ``evaluate(origins (n, 3), dirs (n, 3), depths (n, K)) -> (sigma_raw (n, K), features (n, K, C))``.
Evaluate = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def render_with(
    tri: TriplaneData, camera: np.ndarray, settings: RenderSettings, evaluate: Evaluate
) -> dict[str, np.ndarray]:
    """:func:`render_reference`'s sampler and compositing around any field ``evaluate`` (the decoder
    in :func:`render_reference`, the baked field's lookup in :mod:`lp3d.render.baked`); ``settings``
    resolved and the scene bounds ``tri``'s."""
    cams, batched = validate_camera(camera)
    B, R = cams.shape[0], settings.resolution
    S, N = settings.depth_resolution, settings.depth_resolution_importance
    origins, dirs = (a.reshape(-1, 3) for a in rays_from_cameras(cams, R))
    n_total = origins.shape[0]
    jitter = u_all = None
    if not settings.deterministic:
        jitter = coarse_jitter(settings.seed, n_total, S)
        u_all = sorted_importance_u(settings.seed, n_total, N) if N > 0 else None

    features: np.ndarray | None = None
    depth = np.empty(n_total)
    weights_sum = np.empty(n_total)
    t_min, t_max = np.inf, -np.inf
    for lo in range(0, n_total, _CHUNK_RAYS):
        sl = slice(lo, min(lo + _CHUNK_RAYS, n_total))
        o, d = origins[sl], dirs[sl]
        t = sample_stratified(
            o.shape[0],
            depth_resolution=S,
            ray_start=tri.ray_start,
            ray_end=tri.ray_end,
            jitter=None if jitter is None else jitter[sl],
        )
        sigma_raw, feat = evaluate(o, d, t)
        if N > 0:
            coarse = march(t, sigma_raw, feat, white_back=settings.white_back)
            t_fine = sample_importance(t, coarse.weights, N, None if u_all is None else u_all[sl])
            sigma_raw_fine, feat_fine = evaluate(o, d, t_fine)
            # Merge coarse then fine and sort by depth; the coarse samples are reused, not recomputed.
            t = np.concatenate([t, t_fine], axis=-1)
            order = np.argsort(t, axis=-1, kind="stable")
            t = np.take_along_axis(t, order, axis=-1)
            both = np.concatenate([sigma_raw, sigma_raw_fine], axis=-1)
            sigma_raw = np.take_along_axis(both, order, axis=-1)
            feat = np.take_along_axis(np.concatenate([feat, feat_fine], axis=-2), order[..., None], axis=-2)
        result = march(t, sigma_raw, feat, white_back=settings.white_back)
        t_min, t_max = min(t_min, float(t.min())), max(t_max, float(t.max()))
        if features is None:
            features = np.empty((n_total, result.features.shape[-1]))
        features[sl], depth[sl], weights_sum[sl] = result.features, result.depth, result.weights_sum

    # EG3D clamps with the min/max over the whole batch tensor of sample depths (matters only for W = 0).
    depth = np.clip(depth, t_min, t_max)
    assert features is not None
    out = {
        "features": features.reshape(B, R, R, -1).transpose(0, 3, 1, 2),
        "depth": depth.reshape(B, R, R),
        "weights_sum": weights_sum.reshape(B, R, R),
    }
    out["rgb"] = out["features"][:, :3]
    if not batched:
        out = {k: v[0] for k, v in out.items()}
    return {k: np.ascontiguousarray(v) for k, v in out.items()}
