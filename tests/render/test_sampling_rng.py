"""lp3d.render.sampling_rng against an independent pure-Python (int) implementation of
docs/sampling-rng.md."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lp3d.render.sampling_rng import coarse_jitter, pcg_hash, rand_u32, sorted_importance_u, uniform01

M32 = 0xFFFFFFFF


def pcg_py(v: int) -> int:
    state = (v * 747796405 + 2891336453) & M32
    word = (((state >> ((state >> 28) + 4)) ^ state) * 277803737) & M32
    return ((word >> 22) ^ word) & M32


def rand_py(seed: int, ray: int, stream: int, k: int) -> int:
    return pcg_py((pcg_py((pcg_py(seed ^ ((stream * 0x9E3779B9) & M32)) + ray) & M32) + k) & M32)


def uniform_py(x: int) -> float:
    return (x >> 8) / 2**24


def test_pcg_hash_vectors() -> None:
    # Stated test vectors (cross-checked by the pure-Python implementation); other renderers use them too.
    vectors = {0: 129708002, 1: 2831084092, 0xFFFFFFFF: 3861530882}
    for v, expected in vectors.items():
        assert pcg_py(v) == expected
        assert int(pcg_hash(v)) == expected
    out = pcg_hash(np.array(list(vectors), dtype=np.uint32))
    assert out.dtype == np.uint32
    assert out.tolist() == list(vectors.values())


@given(st.lists(st.integers(min_value=0, max_value=M32), min_size=1, max_size=50))
def test_pcg_hash_matches_python(values: list[int]) -> None:
    assert pcg_hash(np.array(values, dtype=np.uint32)).tolist() == [pcg_py(v) for v in values]


@given(
    st.integers(0, M32),
    st.integers(0, M32),
    st.integers(0, 1),
    st.integers(0, 300),
)
def test_rand_u32_matches_python(seed: int, ray: int, stream: int, k: int) -> None:
    assert int(rand_u32(seed, ray, stream, k)) == rand_py(seed, ray, stream, k)


def test_rand_u32_broadcasts_and_raises_no_warnings() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # uint32 wrap-around must not warn
        out = rand_u32(0xFFFFFFFF, np.arange(5)[:, None], 1, np.arange(7)[None, :])
        pcg_hash(0xFFFFFFFF)
        coarse_jitter(0xFFFFFFFF, 3, 4)
        sorted_importance_u(0xFFFFFFFF, 3, 4)
    assert out.shape == (5, 7) and out.dtype == np.uint32
    assert out[3, 6] == rand_py(0xFFFFFFFF, 3, 1, 6)


def test_uniform01() -> None:
    assert uniform01(0) == 0.0
    assert uniform01(0xFFFFFFFF) == (2**24 - 1) / 2**24
    assert uniform01(0x100) == 2**-24
    x = uniform01(np.array([0xFFFFFFFF], dtype=np.uint32))
    assert np.float32(x[0]) == x[0]  # exact in float32


def test_coarse_jitter_matches_spec() -> None:
    U = coarse_jitter(42, 6, 5)
    assert U.shape == (6, 5) and U.dtype == np.float64
    assert np.all((U >= 0) & (U < 1))
    for ray in range(6):
        for k in range(5):
            assert U[ray, k] == uniform_py(rand_py(42, ray, 0, k))


def test_sorted_importance_u_matches_spec() -> None:
    n, N = 4, 6
    u = sorted_importance_u(7, n, N)
    assert u.shape == (n, N)
    assert np.all(np.diff(u, axis=1) >= 0) and np.all((u >= 0) & (u < 1))
    for ray in range(n):
        e = [-math.log(1.0 - uniform_py(rand_py(7, ray, 1, j))) for j in range(N + 1)]
        total = math.fsum(e)
        expected = [math.fsum(e[: j + 1]) / total for j in range(N)]
        np.testing.assert_allclose(u[ray], expected, rtol=1e-14)


def test_seeds_and_streams_differ() -> None:
    assert not np.array_equal(coarse_jitter(0, 8, 8), coarse_jitter(1, 8, 8))
    assert np.array_equal(coarse_jitter(3, 8, 8), coarse_jitter(3, 8, 8))
    # The coarse and importance streams draw different numbers for the same (seed, ray, k).
    assert not np.array_equal(rand_u32(0, np.arange(8), 0, 0), rand_u32(0, np.arange(8), 1, 0))


def test_distributions() -> None:
    U = coarse_jitter(5, 20000, 4)
    assert U.mean() == pytest.approx(0.5, abs=0.01)
    assert U.std() == pytest.approx(math.sqrt(1 / 12), abs=0.01)
    N = 4
    u = sorted_importance_u(5, 20000, N)
    # Order statistics of N iid uniforms: E[u_(j)] = (j + 1) / (N + 1).
    np.testing.assert_allclose(u.mean(axis=0), np.arange(1, N + 1) / (N + 1), atol=0.01)
