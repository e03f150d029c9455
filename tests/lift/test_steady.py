"""``lp3d.lift.steady.SteadyPlanes``: the centred average behind ``lp3d video --steady``.
How steady it makes a real lift is ``bench/video_steadiness.py``; these check the filter itself
against a direct computation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lp3d.lift.steady import SteadyPlanes


def _stream(steady: SteadyPlanes, frames: np.ndarray) -> tuple[list[int], np.ndarray]:
    out = []
    for i, f in enumerate(frames):
        out += steady.push(i, f)
    out += steady.flush()
    return [i for i, _ in out], np.stack([p for _, p in out])


def _direct(frames: np.ndarray, sigma: float) -> np.ndarray:
    """Each frame's Gaussian-weighted mean over ``|j| <= ceil(2 sigma)`` neighbours that exist."""
    r, n = math.ceil(2 * sigma), len(frames)
    out = []
    for i in range(n):
        js = np.arange(max(0, i - r), min(n, i + r + 1))
        w = np.exp(-0.5 * ((js - i) / sigma) ** 2)
        out.append(np.tensordot(w / w.sum(), frames[js], axes=1))
    return np.stack(out)


@pytest.mark.parametrize("sigma, n", [(1.5, 12), (2.0, 3), (0.7, 1), (3.0, 40)])
def test_matches_the_direct_average_and_keeps_order(sigma, n) -> None:
    frames = np.random.default_rng(0).normal(size=(n, 2, 3, 4)).astype(np.float32)
    order, out = _stream(SteadyPlanes(sigma), frames)
    assert order == list(range(n))
    np.testing.assert_allclose(out, _direct(frames.astype(np.float64), sigma), rtol=1e-5, atol=1e-6)
    assert out.dtype == np.float32


def test_no_lag_a_steady_turn_is_kept_where_the_window_is_whole() -> None:
    """Symmetric weights reproduce a linear change exactly: a turning head is not pulled back."""
    frames = np.arange(20, dtype=np.float64)[:, None] * np.ones((1, 5))
    steady = SteadyPlanes(2.0)
    _, out = _stream(steady, frames)
    r = steady.radius
    np.testing.assert_allclose(out[r:-r], frames[r:-r], atol=1e-12)


def test_frames_come_out_radius_late_and_memory_is_bounded() -> None:
    steady = SteadyPlanes(1.0)  # radius 2
    got = [len(steady.push(i, np.zeros(3))) for i in range(10)]
    assert got == [0, 0, 1, 1, 1, 1, 1, 1, 1, 1]
    assert len(steady._planes) <= 2 * steady.radius + 1
    assert len(steady.flush()) == 2


def test_sigma_zero_passes_frames_through() -> None:
    steady = SteadyPlanes(0.0)
    x = np.arange(6.0)
    ((item, planes),) = steady.push("a", x)
    assert item == "a" and planes is not x and np.array_equal(planes, x)
    assert steady.flush() == []


@pytest.mark.parametrize("sigma", [-1.0, float("nan"), float("inf"), 1e6, "2"])
def test_bad_sigma_is_refused(sigma) -> None:
    with pytest.raises(ValueError, match="sigma"):
        SteadyPlanes(sigma)
