"""PyTorch twin of the EG3D triplane renderer: differentiable, batched, device-agnostic.

Training needs gradients through the renderer, so this module re-implements, in torch, exactly the
semantics of ``docs/eg3d-rendering.md`` that ``lp3d_render`` (WGSL) and the float64 NumPy reference
(``lp3d.render.reference``) implement. The stages (:mod:`lp3d.render.torch_stages`, re-exported here)
follow the data flow and have the reference's names, arguments and quantities (``t`` depths,
``sigma_raw`` raw densities, ``feat`` features):

``rays_from_cameras`` → ``sample_stratified`` → ``sample_triplane`` → ``decode`` → ``march`` (coarse)
→ ``sample_importance`` / ``sample_pdf`` → ``sample_triplane`` → ``decode`` → ``unify_samples`` →
``march`` → ``clamp_depth``.

``render_rays`` runs that pipeline on given rays; ``render_torch`` validates its inputs, builds the
rays from EG3D 25-float camera labels, renders in chunks of rays and assembles images;
``render_with_twin`` is a NumPy-in, NumPy-out convenience with the reference's interface.

Shapes: ``B`` cameras, ``M = R*R`` rays per camera, ``S``/``N`` coarse/fine samples per ray,
``K`` samples in a marched list, ``C = 32`` channels, ``P`` triplanes (1 shared or one per camera).
Everything follows the dtype of ``planes`` (float32 as in EG3D; float64 for gradient checks) and the
device of ``planes``.

Where this twin knowingly differs from EG3D's code (values are identical):

* The depth of a ray with zero total weight is 0/0 = NaN in EG3D, which ``nan_to_num`` turns into +inf
  and the clamp into the batch's largest sample depth. The forward values here are the same, but the
  division is guarded so that the backward pass gives 0 rather than NaN on such rays.
* The coarse march that feeds importance sampling runs under ``torch.no_grad``: EG3D only uses its
  weights inside ``no_grad`` anyway, so this saves memory without changing any gradient.
* Opacity is computed as ``-expm1(-sigma * delta)`` rather than ``1 - exp(-sigma * delta)``: the same
  function, evaluated without cancellation, so float32 renders of faint rays agree with the float64
  reference (EG3D's float32 form can be off by several percent in the depth of nearly empty rays).
* Deterministic mode (the lp3d default) uses no coarse jitter and EG3D's ``det=True`` importance draw;
  jittered mode takes its random numbers from ``lp3d.render.sampling_rng`` (``docs/sampling-rng.md``) so that
  all lp3d renderers draw the same ones, rather than from ``torch.rand``.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from lp3d.render import sampling_rng  # the counter-based RNG shared by every lp3d renderer
from lp3d.render.camera import validate_camera
from lp3d.render.settings import (
    HIDDEN,
    N_CHANNELS,
    N_OUT,
    RenderSettings,
    SceneBounds,
    resolve_settings,
)
from lp3d.render.torch_stages import (
    MarchResult,
    clamp_depth,
    decode,
    evaluate,
    march,
    rays_from_cameras,
    sample_importance,
    sample_pdf,
    sample_stratified,
    sample_triplane,
    unify_samples,
)
from lp3d.render.triplane import PLANE_AXES, TriplaneData

__all__ = [
    "DEFAULT_RAY_CHUNK",
    "PLANE_AXES",
    "MarchResult",
    "TriplaneLike",
    "clamp_depth",
    "decode",
    "march",
    "rays_from_cameras",
    "render_rays",
    "render_torch",
    "render_with_twin",
    "sample_importance",
    "sample_pdf",
    "sample_stratified",
    "sample_triplane",
    "unify_samples",
]

#: Rays rendered at once by ``render_torch`` (over all cameras). With 48+48 samples a chunk peaks at
#: about 2 GB without autograd; gradients keep every chunk's graph alive, so chunking bounds memory
#: only for inference renders (e.g. 512² previews), never for training steps.
DEFAULT_RAY_CHUNK = 32768


class TriplaneLike(Protocol):
    """What ``render_with_twin`` reads from a triplane (e.g. ``lp3d.render.triplane.TriplaneData``).

    ``planes`` (3, 32, H, W) float16/float32; effective decoder weights ``w0`` (64, 32), ``b0`` (64,),
    ``w1`` (33, 64), ``b1`` (33,); scalars ``box_warp``, ``ray_start``, ``ray_end``.
    """

    planes: np.ndarray
    w0: np.ndarray
    b0: np.ndarray
    w1: np.ndarray
    b1: np.ndarray
    box_warp: float | np.ndarray
    ray_start: float | np.ndarray
    ray_end: float | np.ndarray


def render_rays(
    planes: Tensor,
    w0: Tensor,
    b0: Tensor,
    w1: Tensor,
    b1: Tensor,
    ray_origins: Tensor,
    ray_directions: Tensor,
    *,
    bounds: SceneBounds,
    settings: RenderSettings,
    coarse_jitter: Tensor | None = None,
    importance_u: Tensor | None = None,
    t_fine: Tensor | None = None,
    clamp: bool = True,
) -> dict[str, Tensor]:
    """EG3D's ``ImportanceRenderer.forward`` on given rays, without input validation (see ``render_torch``).

    Args:
        planes: (P, 3, 32, H, W), P = B (one triplane per camera) or 1 (shared).
        w0, b0, w1, b1: effective decoder weights, (64, 32), (64,), (33, 64), (33,).
        ray_origins, ray_directions: (B, M, 3), unit directions.
        bounds: the scene (``box_warp``, ``ray_start``, ``ray_end``).
        settings: ``depth_resolution``, ``depth_resolution_importance`` (0: coarse samples only) and
            ``white_back`` are used; resolution and sampling mode are the caller's (rays, jitter, u).
        coarse_jitter: U (B, M, S) in [0, 1), or None (no jitter).
        importance_u: u (B, M, N) in [0, 1], or None (EG3D's ``det=True``: linspace(0, 1, N)).
        t_fine: (B, M, N) fine depths to use instead of drawing them from the coarse pass, e.g. to hold
            them fixed in a finite-difference gradient check.
        clamp: clamp depths to the range of all sample depths of this call (EG3D); ``render_torch``
            clamps once over all its chunks instead.

    Returns:
        ``features`` (B, M, 32), ``depth`` (B, M), ``weights_sum`` (B, M); ``t_range`` (2,), the min and
        max over all sample depths; and ``t_fine`` (B, M, N) when N > 0.
    """

    def points_at(t: Tensor) -> Tensor:  # (B, M, K) depths → (B, M, K, 3) world points
        return ray_origins.unsqueeze(-2) + t.unsqueeze(-1) * ray_directions.unsqueeze(-2)

    box_warp, depth_resolution_importance = bounds.box_warp, settings.depth_resolution_importance
    t = sample_stratified(
        ray_origins.shape[:2],
        depth_resolution=settings.depth_resolution,
        ray_start=bounds.ray_start,
        ray_end=bounds.ray_end,
        jitter=coarse_jitter,
        dtype=ray_origins.dtype,
        device=ray_origins.device,
    )
    sigma_raw, feat = evaluate(planes, w0, b0, w1, b1, points_at(t), box_warp=box_warp)
    out: dict[str, Tensor] = {}

    if depth_resolution_importance > 0:
        if t_fine is None:
            # Only the coarse weights are used from this pass, and they get no gradient (as in EG3D).
            with torch.no_grad():
                coarse = march(t, sigma_raw, feat)
            t_fine = sample_importance(t, coarse.weights, depth_resolution_importance, importance_u)
        sigma_raw_fine, feat_fine = evaluate(planes, w0, b0, w1, b1, points_at(t_fine), box_warp=box_warp)
        t, sigma_raw, feat = unify_samples(t, sigma_raw, feat, t_fine, sigma_raw_fine, feat_fine)
        out["t_fine"] = t_fine

    result = march(t, sigma_raw, feat, white_back=settings.white_back)
    t_all = t.detach()
    out.update(
        features=result.features,
        depth=clamp_depth(result.depth, t) if clamp else result.depth,
        weights_sum=result.weights_sum,
        t_range=torch.stack([t_all.min(), t_all.max()]),
    )
    return out


# --------------------------------------------------------------------------------------------------
# Validation and the public entry points.
# --------------------------------------------------------------------------------------------------


def _check_tensor(name: str, value: object, shape: tuple[int, ...], like: Tensor) -> Tensor:
    """Shape, dtype, device and finiteness of a decoder weight; returns it unchanged."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if tuple(value.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(value.shape)}")
    if value.dtype != like.dtype or value.device != like.device:
        raise ValueError(
            f"{name} must match planes' dtype and device ({like.dtype}, {like.device}), "
            f"got ({value.dtype}, {value.device})"
        )
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} must be finite (it contains NaN or Inf)")
    return value


def _validate(
    planes: object,
    w0: object,
    b0: object,
    w1: object,
    b1: object,
    cameras: object,
    ray_chunk: object,
) -> tuple[Tensor, Tensor]:
    """Checks every tensor input; returns planes as (P, 3, 32, H, W) and cameras as (B, 25)."""
    if not isinstance(planes, Tensor):
        raise TypeError(f"planes must be a torch.Tensor, got {type(planes).__name__}")
    if planes.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"planes must be float32 (as in EG3D) or float64, got {planes.dtype}")
    if (
        planes.ndim not in (4, 5)
        or tuple(planes.shape[-4:-2]) != (3, N_CHANNELS)
        or min(planes.shape[-2:]) < 1
    ):
        raise ValueError(
            f"planes must have shape (3, {N_CHANNELS}, H, W) or (B, 3, {N_CHANNELS}, H, W), "
            f"got {tuple(planes.shape)}"
        )
    if planes.ndim == 5 and planes.shape[0] < 1:
        raise ValueError("planes must hold at least one triplane, got a batch of 0")
    if not bool(torch.isfinite(planes).all()):
        raise ValueError("planes must be finite (it contains NaN or Inf)")
    _check_tensor("w0", w0, (HIDDEN, N_CHANNELS), planes)
    _check_tensor("b0", b0, (HIDDEN,), planes)
    _check_tensor("w1", w1, (N_OUT, HIDDEN), planes)
    _check_tensor("b1", b1, (N_OUT,), planes)

    if not isinstance(cameras, Tensor):
        raise TypeError(f"cameras must be a torch.Tensor, got {type(cameras).__name__}")
    try:  # the one camera check of lp3d (shape, finiteness, rigid pose, intrinsics layout)
        validate_camera(cameras.detach().to("cpu", torch.float64).numpy())
    except ValueError as error:
        raise ValueError(f"cameras: {error}") from None
    # Rays are built in the planes' dtype, as EG3D builds them in float32.
    cams = cameras.reshape(-1, 25).to(device=planes.device, dtype=planes.dtype)
    tri = planes if planes.ndim == 5 else planes.unsqueeze(0)
    if planes.ndim == 5 and tri.shape[0] != cams.shape[0]:
        raise ValueError(
            f"planes hold {tri.shape[0]} triplanes but cameras hold {cams.shape[0]} cameras; give one "
            "triplane per camera, or planes of shape (3, 32, H, W) shared by all cameras"
        )

    if isinstance(ray_chunk, bool) or not isinstance(ray_chunk, int) or ray_chunk < 1:
        raise ValueError(f"ray_chunk must be a positive int, got {ray_chunk!r}")
    return tri, cams


def _random_draws(
    seed: int, n_rays: int, settings: RenderSettings, like: Tensor
) -> tuple[Tensor, Tensor | None]:
    """The jittered mode's coarse U (n_rays, S) and sorted importance u (n_rays, N)
    (:mod:`lp3d.render.sampling_rng`)."""
    jitter = torch.as_tensor(sampling_rng.coarse_jitter(seed, n_rays, settings.depth_resolution))
    jitter = jitter.to(device=like.device, dtype=like.dtype)
    if settings.depth_resolution_importance == 0:
        return jitter, None
    u = torch.as_tensor(sampling_rng.sorted_importance_u(seed, n_rays, settings.depth_resolution_importance))
    return jitter, u.to(device=like.device, dtype=like.dtype)


def render_torch(
    planes: Tensor,
    w0: Tensor,
    b0: Tensor,
    w1: Tensor,
    b1: Tensor,
    cameras: Tensor,
    settings: RenderSettings | None = None,
    *,
    bounds: SceneBounds | None = None,
    ray_chunk: int = DEFAULT_RAY_CHUNK,
    **overrides: Any,
) -> dict[str, Tensor]:
    """Render triplanes from EG3D cameras, differentiably, with EG3D's renderer semantics.

    Args:
        planes: (B, 3, 32, H, W), one triplane per camera (as in training), or (3, 32, H, W) shared by
            all cameras; float32 or float64. Its dtype and device are those of the render.
        w0, b0, w1, b1: effective decoder weights (64, 32), (64,), (33, 64), (33,), same dtype/device.
        cameras: (B, 25) or (25,) EG3D labels; cast to the planes' dtype and device.
        settings: :class:`~lp3d.render.settings.RenderSettings` (default ``RenderSettings()``; exact, no
            skips): R = ``resolution`` rays per side, S = ``depth_resolution`` coarse and N =
            ``depth_resolution_importance`` fine samples (N = 0: coarse only), ``white_back``;
            ``deterministic``: no coarse jitter and ``det=True`` importance draw, otherwise the draws of
            ``lp3d.render.sampling_rng`` for ``seed`` (ray index ``b * R * R + row * R + col``).
        bounds: :class:`~lp3d.render.settings.SceneBounds` (default: EG3D's FFHQ scene).
        ray_chunk: rays rendered at once (over all cameras), to bound memory; does not change results.
        **overrides: fields of either, e.g. ``resolution=64`` or ``ray_start=2.0``.

    Returns:
        ``features`` (B, 32, R, R) in about [-1, 1], ``rgb`` (B, 3, R, R) (= features[:, :3]),
        ``depth`` (B, R, R) and ``weights_sum`` (B, R, R). The B axis is dropped when ``cameras`` is
        (25,) and ``planes`` is (3, 32, H, W). Depths are clamped to the range of all sample depths of
        the whole batch (EG3D's behaviour; it matters only for rays with zero total weight).

    Raises:
        ValueError: naming the offending input (shape, dtype, device, finiteness, settings).
    """
    settings, bounds = resolve_settings(settings, overrides, bounds)
    settings.require_exact("the torch twin")
    tri, cams = _validate(planes, w0, b0, w1, b1, cameras, ray_chunk)
    resolution = settings.resolution
    n_cams, n_rays = cams.shape[0], resolution * resolution
    s, n = settings.depth_resolution, settings.depth_resolution_importance

    ray_origins, ray_directions = rays_from_cameras(cams, resolution)
    jitter = u = None
    if not settings.deterministic:
        flat_jitter, flat_u = _random_draws(settings.seed, n_cams * n_rays, settings, tri)
        jitter = flat_jitter.reshape(n_cams, n_rays, s)
        u = None if flat_u is None else flat_u.reshape(n_cams, n_rays, n)

    per_chunk = max(1, ray_chunk // n_cams)  # rays per camera in one chunk
    chunks: list[dict[str, Tensor]] = []
    for lo in range(0, n_rays, per_chunk):
        part = slice(lo, min(lo + per_chunk, n_rays))
        chunk = render_rays(
            tri,
            w0,
            b0,
            w1,
            b1,
            ray_origins[:, part],
            ray_directions[:, part],
            bounds=bounds,
            settings=settings,
            coarse_jitter=None if jitter is None else jitter[:, part],
            importance_u=None if u is None else u[:, part],
            clamp=False,
        )
        chunks.append(chunk)
    joined = {key: torch.cat([c[key] for c in chunks], dim=1) for key in ("features", "depth", "weights_sum")}
    # EG3D clamps to the min/max over the sample depths of the whole batch, so clamp after all chunks.
    ranges = torch.stack([c["t_range"] for c in chunks])
    depth = torch.clamp(joined["depth"], ranges[:, 0].min(), ranges[:, 1].max())

    side = (n_cams, resolution, resolution)
    features = joined["features"].transpose(1, 2).reshape(n_cams, N_CHANNELS, resolution, resolution)
    result = {
        "features": features,
        "rgb": features[:, :3],
        "depth": depth.reshape(side),
        "weights_sum": joined["weights_sum"].reshape(side),
    }
    if cameras.ndim == 1 and planes.ndim == 4:
        result = {key: value[0] for key, value in result.items()}
    return result


def render_with_twin(
    triplane: TriplaneLike,
    camera: np.ndarray,
    settings: RenderSettings | None = None,
    *,
    device: str | torch.device | None = None,
    ray_chunk: int = DEFAULT_RAY_CHUNK,
    **overrides: Any,
) -> dict[str, np.ndarray]:
    """NumPy in, NumPy out: render a triplane object with the twin in float32, without autograd.

    Args:
        triplane: planes (3, 32, H, W), effective decoder weights w0, b0, w1, b1, and the scene scalars
            box_warp, ray_start, ray_end (e.g. ``lp3d.render.triplane.TriplaneData``); validated as one.
        camera: (25,) or (B, 25) EG3D label(s).
        settings, **overrides: as in ``render_torch``; the bounds are the triplane's (overridable too).
        device: where to render (default CPU).
        ray_chunk: rays rendered at once.

    Raises:
        ValueError: naming the bad field of the triplane or camera, or the bad setting.

    Returns:
        float32 arrays ``features`` ([B,] 32, R, R), ``rgb`` ([B,] 3, R, R), ``depth`` ([B,] R, R) and
        ``weights_sum`` ([B,] R, R); B only when ``camera`` is (B, 25).
    """

    tri = _as_triplane_data(triplane)
    try:
        cams, batched = validate_camera(camera)
    except ValueError as error:
        raise ValueError(f"camera: {error}") from None

    def tensor(array: np.ndarray) -> Tensor:
        return torch.as_tensor(np.asarray(array, dtype=np.float32), device=device)

    with torch.no_grad():
        result = render_torch(
            tensor(tri.planes),  # float16 planes are rendered in float32, as the other renderers do
            tensor(tri.w0),
            tensor(tri.b0),
            tensor(tri.w1),
            tensor(tri.b1),
            tensor(cams if batched else cams[0]),
            settings,
            bounds=tri.bounds,
            ray_chunk=ray_chunk,
            **overrides,
        )
    return {key: np.ascontiguousarray(value.cpu().numpy(), dtype=np.float32) for key, value in result.items()}


def _as_triplane_data(triplane: object) -> TriplaneData:
    """A validated ``TriplaneData`` from any object with the triplane attributes."""
    if isinstance(triplane, TriplaneData):
        triplane.validate()
        return triplane
    names = ("planes", "w0", "b0", "w1", "b1", "box_warp", "ray_start", "ray_end")
    missing = [name for name in names if not hasattr(triplane, name)]
    if missing:
        raise TypeError(f"triplane must have the attributes {', '.join(names)}; missing {', '.join(missing)}")
    return TriplaneData(**{name: getattr(triplane, name) for name in names})
