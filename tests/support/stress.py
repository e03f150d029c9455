"""The stress tests' scenes, cameras and checks (``tests/render/test_stress.py`` explains the method:
invariants everywhere, and a tolerance derived from the scene's float64 sensitivity)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from hypothesis import settings

import lp3d_render
from lp3d.render.camera import FFHQ_FOCAL, intrinsics, pack_label
from lp3d.render.reference import (
    march,
    rays_from_cameras,
    render_reference,
    sample_importance,
    sample_stratified,
    sample_triplane,
    sigmoid,
    softplus,
)
from lp3d.render.triplane import TriplaneData
from support.scenes import Scene, smooth_planes

#: float32 unit roundoff and the float32 spacing just above 1.
U32 = 2.0**-24
ULP1 = 2.0**-23
#: Renders are tiny so lavapipe stays fast; the kernel has no size-specific code paths.
KW = {"resolution": 7, "depth_resolution": 12, "depth_resolution_importance": 12}
#: Tolerance on features, rgb, depth and weights_sum for well-conditioned scenes.
TOL = 1e-4
#: Tolerance = SENS_GAIN * measured float64 sensitivity + TOL.
SENS_GAIN = 4.0
#: Largest float64 sensitivity for which a scene counts as well conditioned and is held to TOL itself
#: (a fifth of it, as test_render_parity.py's conditioning check).
WELL_CONDITIONED = TOL / 5
#: Depth is compared only where the reference's weights_sum is at least this.
FAINT = 1e-9
KEYS = ("features", "rgb", "depth", "weights_sum")
HYPOTHESIS = settings(max_examples=40, deadline=None, derandomize=True, print_blob=True)


# ------------------------------------------------------------------------------------------- scenes


def make_planes(kind: str, rng: np.random.Generator, size: int, amplitude: float, dtype=np.float32):
    """(3, 32, size, size) planes: ``smooth`` (band-limited, tapered), ``noise`` (white) or ``constant``."""
    if kind == "smooth":
        p = smooth_planes(rng, size, size)
    elif kind == "noise":
        p = rng.standard_normal((3, 32, size, size))
    elif kind == "constant":
        p = np.broadcast_to(rng.standard_normal((3, 32, 1, 1)), (3, 32, size, size))
    else:
        raise ValueError(kind)
    return (amplitude * p).astype(dtype)


def make_decoder(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """EG3D-scaled random decoder (effective weights, float64; TriplaneData stores them as float32)."""
    return {
        "w0": rng.standard_normal((64, 32)) / np.sqrt(32),
        "b0": 0.1 * rng.standard_normal(64),
        "w1": rng.standard_normal((33, 64)) / 8,
        "b1": 0.1 * rng.standard_normal(33),
    }


def build(planes: np.ndarray, dec: dict, *, ray_start=2.25, ray_end=3.3, box_warp=1.0) -> Scene:
    data = TriplaneData(planes=planes, **dec, box_warp=box_warp, ray_start=ray_start, ray_end=ray_end)
    return Scene(data=data, native=data.to_native())


def decoder_at_samples(data: TriplaneData, cameras: np.ndarray, kw: dict, *, float32: bool = False):
    """``(t, outputs)``: the depths of every ray's samples, (n_rays, K), and the decoder outputs
    before activation there, (n_rays, K, 33), in float64; with ``float32`` also the outputs evaluated
    in float32 the way the kernel does (one product-sum at a time) as a third element.

    The samples are the reference's deterministic ones: S coarse, plus N importance samples when
    ``depth_resolution_importance`` > 0, merged in depth order."""
    origins, dirs = (a.reshape(-1, 3) for a in rays_from_cameras(cameras, kw["resolution"]))
    w0, b0, w1, b1 = (np.asarray(a, np.float64) for a in (data.w0, data.b0, data.w1, data.b1))

    def features(t: np.ndarray) -> np.ndarray:
        points = origins[:, None] + t[..., None] * dirs[:, None]
        return sample_triplane(data.planes.astype(np.float64), points, box_warp=data.box_warp)

    t = sample_stratified(
        origins.shape[0],
        depth_resolution=kw["depth_resolution"],
        ray_start=data.ray_start,
        ray_end=data.ray_end,
    )
    f = features(t)
    if kw["depth_resolution_importance"] > 0:
        s = (softplus(f @ w0.T + b0) @ w1[0] + b1[0])[..., None]
        coarse = march(t, s[..., 0], np.zeros_like(s))
        t = np.concatenate([t, sample_importance(t, coarse.weights, kw["depth_resolution_importance"])], -1)
        order = np.argsort(t, axis=-1, kind="stable")
        t = np.take_along_axis(t, order, axis=-1)
        f = features(t)
    out = softplus(f @ w0.T + b0) @ w1.T + b1
    if not float32:
        return t, out

    def layer(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
        acc = np.zeros((*x.shape[:-1], w.shape[0]), np.float32)
        for j in range(w.shape[1]):
            acc += x[..., j : j + 1] * w[:, j]
        return acc + b

    pre = layer(f.astype(np.float32), data.w0, data.b0)
    h = np.where(pre > 20, pre, np.log1p(np.exp(np.minimum(pre, np.float32(20))))).astype(np.float32)
    return t, out, layer(h, data.w1, data.b1).astype(np.float64)


def span_decoder(
    planes: np.ndarray,
    dec: dict,
    cameras: np.ndarray,
    kw: dict,
    *,
    density: tuple[float, float],
    logit_span: float,
    **bounds,
) -> Scene:
    """The scene with decoder rows rescaled so that, over the coarse samples of these renders, the raw
    density spans exactly ``density = (lo, hi)`` and the 32 feature logits reach +-``logit_span``
    (importance samples fall between coarse ones and may reach a little further)."""
    base = build(planes, dec, **bounds).data
    _, out = decoder_at_samples(base, cameras, {**kw, "depth_resolution_importance": 0})
    w1, b1 = np.array(dec["w1"], np.float64), np.array(dec["b1"], np.float64)
    lo, hi = density
    s_min, s_max = float(out[..., 0].min()), float(out[..., 0].max())
    if s_max - s_min > 1e-9 * max(1.0, abs(s_max)):
        a = (hi - lo) / (s_max - s_min)
        w1[0] *= a
        b1[0] = a * b1[0] + (lo - a * s_min)
    else:  # the density does not vary over these samples: a constant at the span's centre
        w1[0] = 0.0
        b1[0] = 0.5 * (lo + hi)
    g = logit_span / max(float(np.abs(out[..., 1:]).max()), 1e-30)
    w1[1:] *= g
    b1[1:] *= g
    return build(planes, {**dec, "w1": w1, "b1": b1}, **bounds)


# ------------------------------------------------------------------------------------------ cameras


def axis_camera(forward, down, target, *, distance: float = 2.7, focal: float = FFHQ_FOCAL) -> np.ndarray:
    """Camera with an exact 0/+-1 rotation (columns right, down, forward) whose centre ray passes
    through ``target`` along ``forward``; with an odd resolution that ray's direction is exact."""
    fwd, dn = np.asarray(forward, np.float64), np.asarray(down, np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([np.cross(dn, fwd), dn, fwd], axis=-1)
    c2w[:3, 3] = np.asarray(target, np.float64) - distance * fwd
    return pack_label(c2w, intrinsics(focal))


def rotated(camera: np.ndarray, angle: float, axis=(1.0, 2.0, -1.5)) -> np.ndarray:
    """The camera turned by ``angle`` radians about a world axis through its centre."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    rot = np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)
    out = camera.copy()
    c2w = out[:16].reshape(4, 4)
    c2w[:3, :3] = rot @ c2w[:3, :3]
    out[:16] = c2w.reshape(16)
    return out


# ----------------------------------------------------------------------------------------- checks


def render_gpu(scene: Scene, cameras: np.ndarray, kw: dict, seed: int | None = None) -> dict:
    """GPU render (jittered when ``seed`` is given) with every invariant checked."""
    got = lp3d_render.render(scene.native, cameras, **kw, deterministic=seed is None, seed=seed)
    check_invariants(got, scene.data, kw, jittered=seed is not None)
    return got


def render_ref(data: TriplaneData, cameras: np.ndarray, kw: dict, seed: int | None = None) -> dict:
    jitter = {} if seed is None else {"deterministic": False, "seed": seed}
    return render_reference(data, cameras, **kw, **jitter)


def check_invariants(out: dict, data: TriplaneData, kw: dict, *, jittered: bool = False) -> None:
    for key, value in out.items():
        assert value.dtype == np.float32, key
        bad = ~np.isfinite(value)
        assert not bad.any(), f"{key}: {int(bad.sum())} NaN/Inf values, first at {np.argwhere(bad)[0]}"
    w = out["weights_sum"]
    assert w.min() >= 0.0, f"weights_sum {w.min()!r} < 0"
    assert w.max() <= 1.0, f"weights_sum {w.max()!r} > 1 ({(w.max() - 1.0) / ULP1:.0f} float32 ulps)"
    lo, hi = np.float32(data.ray_start), np.float32(data.ray_end)
    if jittered:  # coarse depths reach up to one jitter step (float32, as the kernel has it) past ray_end
        step = np.float32((data.ray_end - data.ray_start) / (kw["depth_resolution"] - 1))
        hi = np.nextafter(np.float32(hi + step), np.float32(np.inf))
    d = out["depth"]
    assert d.min() >= lo and d.max() <= hi, f"depth [{d.min()!r}, {d.max()!r}] outside [{lo!r}, {hi!r}]"
    # Composited from the unclamped running sum of weights, which may end a few ulps above 1.
    f = out["features"]
    assert f.min() >= -1.002 - 1e-5 and f.max() <= 1.002 + 1e-5, f"features [{f.min()}, {f.max()}]"
    assert np.array_equal(out["rgb"], f[..., :3, :, :])


def errors(got: dict, ref: dict, depth_rays: np.ndarray) -> dict[str, float]:
    """Max abs difference per output; depth only on ``depth_rays`` (reference W >= FAINT)."""
    out = {}
    for key in KEYS:
        e = np.abs(np.asarray(got[key], np.float64) - ref[key])
        if key == "depth":
            e = np.where(depth_rays, e, 0.0)
        out[key] = float(e.max()) if e.size else 0.0
    return out


def perturbations(
    data: TriplaneData, cameras: np.ndarray, decoder_error: np.ndarray
) -> list[tuple[str, TriplaneData, np.ndarray]]:
    """``(term, triplane, cameras)``: the inputs moved by their float32 rounding (module docstring);
    ``decoder_error`` (33,): the decoder outputs' float32 rounding, applied as a uniform offset."""
    cams = np.atleast_2d(cameras)
    eps = U32 * np.maximum(np.linalg.norm(cams[:, [3, 7, 11]], axis=-1), 1.0)  # per camera
    out = []
    fwd = cams[:, [2, 6, 10]]
    diag = np.broadcast_to(np.array([1.0, -1.0, 1.0]) / math.sqrt(3.0), fwd.shape)
    for direction in (fwd, diag):
        shifted = cams.copy()
        shifted[:, [3, 7, 11]] += eps[:, None] * direction
        out.append(("camera shift", data, shifted))
    out.append(("camera rotation", data, np.stack([rotated(c, e) for c, e in zip(cams, eps, strict=True)])))
    for a, b in ((-1, 1), (1, -1), (1, 1), (-1, -1)):
        rs, re = data.ray_start * (1 + a * U32), data.ray_end * (1 + b * U32)
        if rs < re:
            out.append(("depth range", dataclasses.replace(data, ray_start=rs, ray_end=re), cams))
    for sign in (1.0, -1.0):
        out.append(("decoder", dataclasses.replace(data, b1=data.b1 + sign * decoder_error), cams))
    if np.ndim(cameras) == 1:
        out = [(term, d, c[0]) for term, d, c in out]
    return out


def decoder_depth_tilt(t: np.ndarray, s: np.ndarray, e: np.ndarray, rays: np.ndarray) -> float:
    """Largest first-order depth shift, over the rays selected by ``rays``, from raw-density errors
    that differ from sample to sample: depths t, raw densities s and their float32 errors e are
    (n_rays, K) (``decoder_at_samples``).

    An error e_i in interval i's mean raw density m_i + 1 changes sigma_i relatively by
    ``r_i = e_i sigmoid(m_i) / softplus(m_i)``, alpha_i relatively by ``g_i r_i`` with
    ``g_i = x_i / expm1(x_i)`` (x_i = sigma_i delta_i), and the transmittance before i by
    ``sum_{j<i} x_j r_j``. With adversarial signs the weighted mean depth d then moves by up to
    ``sum_i w_i eps_i |t_i - d| / W`` (float64 march)."""
    m = 0.5 * (s[:, :-1] + s[:, 1:]) - 1.0
    sp = softplus(m)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        r = np.where(m < -30.0, 1.0, sigmoid(m) / sp) * 0.5 * (e[:, :-1] + e[:, 1:])
        x = sp * np.diff(t, axis=-1)
        g = np.where(x < 1e-12, 1.0, x / np.expm1(np.minimum(x, 700.0)))
    eps = g * r + np.cumsum(x * r, axis=-1) - x * r
    res = march(t, s, np.zeros((*s.shape, 1)))
    w, big_w = res.weights, res.weights_sum
    t_mid = 0.5 * (t[:, :-1] + t[:, 1:])
    ok = rays & (big_w > 0.0)
    if not ok.any():
        return 0.0
    w, eps, t_mid, big_w = w[ok], eps[ok], t_mid[ok], big_w[ok]
    d = (w * t_mid).sum(axis=-1) / big_w
    return float(((w * eps * np.abs(t_mid - d[:, None])).sum(axis=-1) / big_w).max())


def float64_sensitivity(data: TriplaneData, cameras: np.ndarray, kw: dict, ref: dict, seed=None) -> dict:
    """Largest change of each reference output under the ``perturbations``; depth also gets
    ``decoder_depth_tilt`` (a uniform offset cannot tilt a ray's weights the way rounding can)."""
    t, out, out32 = decoder_at_samples(data, np.atleast_2d(cameras), kw, float32=True)
    err = np.abs(out32 - out)
    mask = ref["weights_sum"] >= FAINT
    sens = dict.fromkeys(KEYS, 0.0)
    for _, d, c in perturbations(data, cameras, err.reshape(-1, 33).max(axis=0)):
        for key, value in errors(render_ref(d, c, kw, seed), ref, mask).items():
            sens[key] = max(sens[key], value)
    tilt = decoder_depth_tilt(t, out[..., 0], err[..., 0], mask.reshape(-1))
    sens["depth"] = max(sens["depth"], tilt)
    return sens


def derived_tolerance(sens: dict, data: TriplaneData) -> dict[str, float]:
    tol = {key: SENS_GAIN * sens[key] + TOL for key in KEYS}
    tol["depth"] += 16 * U32 * data.ray_end
    return tol


def assert_close(got: dict, ref: dict, tol: dict[str, float]) -> dict[str, float]:
    err = errors(got, ref, ref["weights_sum"] >= FAINT)
    bad = {k: f"{err[k]:.3e} > {tol[k]:.3e}" for k in KEYS if not err[k] <= tol[k]}
    assert not bad, f"max abs error vs float64 reference: {bad}"
    return err


def check_scene(
    scene: Scene, cameras: np.ndarray, kw: dict | None = None, *, seed=None, well_conditioned=False
) -> tuple[dict, dict, dict]:
    """Invariants, then the reference comparison with the conditioning-derived tolerance (or TOL
    itself, after checking that the scene really is well conditioned). Returns (got, ref, tol)."""
    kw = KW if kw is None else kw
    got = render_gpu(scene, cameras, kw, seed)
    ref = render_ref(scene.data, cameras, kw, seed)
    sens = float64_sensitivity(scene.data, cameras, kw, ref, seed)
    if well_conditioned:
        worst = max(sens.values())
        assert worst < WELL_CONDITIONED, f"scene is not well conditioned: sensitivity {sens}"
        tol = dict.fromkeys(KEYS, TOL)
    else:
        tol = derived_tolerance(sens, scene.data)
    assert_close(got, ref, tol)
    return got, ref, tol
