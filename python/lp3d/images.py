"""Small image helpers for figures: renderer outputs to uint8, depth to colour, atomic PNG writes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lp3d.atomic import atomic_path


def rgb_to_uint8(rgb: np.ndarray) -> np.ndarray:
    """(3, H, W) renderer RGB in about [-1, 1] -> (H, W, 3) uint8."""
    x = (np.clip(np.asarray(rgb, np.float64), -1.0, 1.0) + 1.0) * 127.5
    return np.round(x).astype(np.uint8).transpose(1, 2, 0)


def depth_to_uint8(
    depth: np.ndarray, weights_sum: np.ndarray | None = None, lo: float | None = None, hi: float | None = None
) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) uint8, near = bright. Rays with weights_sum < 0.5 are black."""
    d = np.asarray(depth, np.float64)
    mask = np.ones_like(d, bool) if weights_sum is None else np.asarray(weights_sum) >= 0.5
    if lo is None or hi is None:
        vals = d[mask] if mask.any() else d
        lo, hi = float(vals.min()), float(vals.max())
    t = np.clip((hi - d) / max(hi - lo, 1e-9), 0.0, 1.0)
    # A warm ramp: black -> red -> yellow -> white.
    rgb = np.stack([np.clip(3 * t, 0, 1), np.clip(3 * t - 1, 0, 1), np.clip(3 * t - 2, 0, 1)], axis=-1)
    rgb[~mask] = 0.0
    return np.round(rgb * 255).astype(np.uint8)


def save_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Writes (H, W, 3) or (H, W) uint8 as PNG atomically (temporary file, then rename)."""
    from PIL import Image

    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG")
    return path


def tile(images: list[np.ndarray], columns: int, pad: int = 2) -> np.ndarray:
    """Grid of equally sized (H, W, 3) uint8 images, row-major, with a dark gutter."""
    h, w, c = images[0].shape
    rows = (len(images) + columns - 1) // columns
    out = np.full((rows * (h + pad) + pad, columns * (w + pad) + pad, c), 24, np.uint8)
    for i, im in enumerate(images):
        r, q = divmod(i, columns)
        out[pad + r * (h + pad) : pad + r * (h + pad) + h, pad + q * (w + pad) : pad + q * (w + pad) + w] = im
    return out
