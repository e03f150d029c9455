"""The counter-based RNG of ``docs/sampling-rng.md``, in NumPy.

Every renderer (WGSL, this NumPy reference, the torch twin) draws the same numbers, so a jittered
render is replayable across implementations. Arithmetic is wrapping uint32: NumPy array operations on
``np.uint32`` wrap silently (only scalar ops warn), so all inputs are turned into arrays first and the
few remaining warnings are silenced with ``np.errstate``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

#: Stream ids: the coarse jitter and the importance draw never share numbers.
STREAM_COARSE = 0
STREAM_IMPORTANCE = 1

_GOLDEN = np.uint32(0x9E3779B9)


def _u32(x: ArrayLike) -> np.ndarray:
    """As a uint32 array, reducing integers mod 2**32 (negative or large ones included)."""
    arr = np.asarray(x)
    if arr.dtype == np.uint32:
        return arr
    if arr.dtype.kind == "b":
        arr = arr.astype(np.int64)
    if arr.dtype.kind == "i":
        return (arr.astype(np.int64) & 0xFFFFFFFF).astype(np.uint32)
    if arr.dtype.kind == "u":
        return (arr.astype(np.uint64) & np.uint64(0xFFFFFFFF)).astype(np.uint32)
    if arr.dtype == object:  # Python ints too large for int64
        return np.array([int(v) & 0xFFFFFFFF for v in arr.ravel()], dtype=np.uint32).reshape(arr.shape)
    raise TypeError(f"expected integers, got dtype {arr.dtype}")


def pcg_hash(v: ArrayLike) -> np.ndarray:
    """PCG-RXS-M-XS hash of uint32 values (any shape); returns uint32 of the same shape."""
    x = np.atleast_1d(_u32(v)).astype(np.uint32)
    with np.errstate(over="ignore"):
        state = x * np.uint32(747796405) + np.uint32(2891336453)
        word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * np.uint32(277803737)
        out = (word >> np.uint32(22)) ^ word
    return out.reshape(np.shape(v))


def rand_u32(seed: int, ray: ArrayLike, stream: int, k: ArrayLike) -> np.ndarray:
    """``pcg_hash(pcg_hash(pcg_hash(seed ^ (stream * 0x9E3779B9)) + ray) + k)``, broadcast over ray and k.

    ``ray`` is the global ray index ``b * R * R + row * R + col`` (taken mod 2**32), ``k`` the sample index.
    """
    s = _u32(seed)
    st = _u32(stream)
    ray_u, k_u = np.broadcast_arrays(_u32(ray), _u32(k))
    with np.errstate(over="ignore"):
        base = pcg_hash(np.atleast_1d(s ^ (st * _GOLDEN)))[0]
        return pcg_hash(pcg_hash(ray_u + base) + k_u)


def uniform01(x: ArrayLike) -> np.ndarray:
    """``float(x >> 8) / 2**24``: a uniform in [0, 1), exact in float32; returned as float64."""
    return (_u32(x) >> np.uint32(8)).astype(np.float64) / float(1 << 24)


def coarse_jitter(seed: int, n_rays: int, S: int) -> np.ndarray:
    """Coarse jitter ``U`` (n_rays, S) float64 in [0, 1) for rays 0..n_rays-1 (stream 0).

    Used as ``t_k = linspace_k + U_k * dj`` with ``dj = (ray_end - ray_start) / (S - 1)``.
    """
    rays = np.arange(n_rays, dtype=np.int64)[:, None]
    ks = np.arange(S, dtype=np.int64)[None, :]
    return uniform01(rand_u32(seed, rays, STREAM_COARSE, ks))


def sorted_importance_u(seed: int, n_rays: int, N: int) -> np.ndarray:
    """Importance draw ``u`` (n_rays, N) float64, ascending per ray (stream 1).

    Exponential spacings: ``e_j = -log(1 - uniform01(rand_u32(seed, ray, 1, j)))`` for j = 0..N and
    ``u_j = (e_0 + ... + e_j) / (e_0 + ... + e_N)``, j < N: the order statistics of N iid uniforms.
    """
    rays = np.arange(n_rays, dtype=np.int64)[:, None]
    js = np.arange(N + 1, dtype=np.int64)[None, :]
    e = -np.log(1.0 - uniform01(rand_u32(seed, rays, STREAM_IMPORTANCE, js)))
    csum = np.cumsum(e, axis=1)
    return csum[:, :N] / csum[:, N:]
