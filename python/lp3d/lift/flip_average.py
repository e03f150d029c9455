"""Flip-averaged encoding: the mean of the encoder's triplane of a photo and the mirror of its triplane
of the photo flipped left to right.

The CPU recipe trains on flipped inputs with mirrored target planes, so both are estimates of the
same head; the encoder is not mirror-symmetric by construction (its pixel-coordinate input channels
are not), and the two estimates err differently, most at the largest input yaws. Averaging them
brings the shipped model's held-out novel views a little closer and raises its identity specificity
(docs/performance.md, "Held-out evaluation") for twice the encoder's work, in one call of twice the
batch. ``lp3d encode``, ``video``, ``demo`` and ``eval`` offer it as ``--flip-average``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from lp3d.render.triplane import mirror_planes


def flip_averaged(encode: Callable[[Any], Any], images: Any) -> Any:
    """``encode`` (images (B, 3, S, S) -> planes (B, 3, C, T, T), numpy or torch) applied flip-averaged:
    ``(encode(x) + mirror(encode(flip(x)))) / 2``, both halves in one call of batch 2B."""
    if isinstance(images, np.ndarray):
        both = encode(np.concatenate([images, images[..., ::-1]]))
    else:
        import torch

        both = encode(torch.cat([images, images.flip(-1)]))
    b = images.shape[0]
    return 0.5 * (both[:b] + mirror_planes(both[b:]))
