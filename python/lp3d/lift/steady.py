"""Steady video: each frame's triplane averaged with its neighbours' (``lp3d video --steady``).

Lifting a video frame by frame makes every frame's head a fresh guess, so small changes of the input
(sensor noise, a hand-held camera's jitter, the crop) make the head shimmer. A video is lifted after
it is recorded, so the average can look both ways: :class:`SteadyPlanes` weights frame ``i + j`` by
``exp(-j² / 2σ²)`` for ``|j| <= radius`` (default ``ceil(2σ)``), renormalised where the window meets
either end of the video. Unlike the causal exponential average of ``--smooth`` it has no lag: a head
that turns is not pulled back towards where it was. It holds ``2 * radius + 1`` frames' planes.

    steady = SteadyPlanes(sigma=1.5)
    for item, planes in frames:
        for item_out, planes_out in steady.push(item, planes):
            ...                                  # frames come out in order, ``radius`` frames late
    for item_out, planes_out in steady.flush():
        ...

``item`` is anything the caller wants back with its frame (the input crop, the frame index).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

#: Largest smoothing width accepted, in frames (a window of 4σ + 1 frames is held in memory).
MAX_SIGMA = 30.0


class SteadyPlanes:
    """Centred Gaussian smoothing of a stream of planes (module docstring); ``sigma = 0`` passes
    every frame through unchanged."""

    def __init__(self, sigma: float, radius: int | None = None) -> None:
        if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and 0 <= sigma <= MAX_SIGMA):
            raise ValueError(f"steady sigma must be a number of frames in [0, {MAX_SIGMA:g}], got {sigma!r}")
        self.sigma = float(sigma)
        self.radius = (math.ceil(2 * sigma) if radius is None else int(radius)) if sigma > 0 else 0
        j = np.arange(-self.radius, self.radius + 1, dtype=np.float64)
        self._weights = np.exp(-0.5 * (j / self.sigma) ** 2) if sigma > 0 else np.ones(1)
        self._items: deque[Any] = deque()
        self._planes: deque[np.ndarray] = deque()
        self._next = 0  # index of the next frame to come out
        self._seen = 0  # frames pushed so far

    def _emit(self, i: int) -> tuple[Any, np.ndarray]:
        """Frame ``i`` smoothed over the frames of its window that exist and are held."""
        first = self._seen - len(self._planes)  # index of the oldest frame held
        lo, hi = max(i - self.radius, first), min(i + self.radius, self._seen - 1)
        w = self._weights[lo - i + self.radius : hi - i + self.radius + 1]
        acc = np.zeros_like(self._planes[0], dtype=np.float64)
        for k, weight in zip(range(lo, hi + 1), w, strict=True):
            acc += weight * self._planes[k - first]
        out = (acc / w.sum()).astype(self._planes[0].dtype)
        return self._items[i - first], out

    def _drop_old(self) -> None:
        # Frames older than the next output's window are not needed again.
        while self._seen - len(self._planes) < self._next - self.radius:
            self._planes.popleft()
            self._items.popleft()

    def _take(self, ready: int) -> list[tuple[Any, np.ndarray]]:
        out = []
        while self._next < ready:
            out.append(self._emit(self._next))
            self._next += 1
            self._drop_old()
        return out

    def push(self, item: Any, planes: np.ndarray) -> list[tuple[Any, np.ndarray]]:
        """Add the next frame; returns the frames whose windows are now complete, in order."""
        self._items.append(item)
        self._planes.append(np.asarray(planes))
        self._seen += 1
        return self._take(self._seen - self.radius)

    def flush(self) -> list[tuple[Any, np.ndarray]]:
        """The last frames, whose windows end with the video."""
        return self._take(self._seen)
