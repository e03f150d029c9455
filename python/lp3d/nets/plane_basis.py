"""The plane basis (:class:`PlaneBasis`, CPU configurations; not in the paper): a learned basis of
planes, mixed by coefficients regressed from DeepLab's features and added to the head's output.

Imports lp3d.nets.encoder_config.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.encoder_config import EncoderConfig


def code_input(features: Tensor, pool: int, colours: Tensor | None) -> Tensor:
    """(B, ``EncoderConfig.code_inputs``): the features average-pooled to ``pool``², flattened, then the
    colour grid (B, 3, P, P) flattened, if given. The basis and the generator read the same vector."""
    x = F.adaptive_avg_pool2d(features, pool).flatten(1)
    return x if colours is None else torch.cat([x, colours.flatten(1)], dim=1)


class PlaneBasis(nn.Module):
    """``forward(aspp features (B, C_a, R, R), colours (B, 3, P, P) | None) -> planes (B, 3·32, T, T)``:
    Σ_k c_k · component_k.

    The coefficients c (B, K) come from an MLP on the features average-pooled to ``basis_pool``²
    (keeping a coarse layout), followed by the input's colour grid when the config has one
    (:func:`code_input`); ``components`` (K, 3·32, R_b, R_b) is learnt, and bilinearly
    upsampled to T. The last layer starts at zero, so an untrained branch adds nothing.
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        k, r = cfg.basis_components, cfg.basis_resolution
        self.pool = cfg.basis_pool
        self.triplane_resolution = cfg.triplane_resolution
        self.coefficients = nn.Sequential(
            nn.Flatten(),  # a no-op on the flat code input, kept so saved weights keep their names
            nn.Linear(cfg.code_inputs, cfg.basis_hidden),
            nn.LeakyReLU(0.01),
            nn.Linear(cfg.basis_hidden, k),
        )
        self.components = nn.Parameter(torch.zeros(k, 3 * cfg.plane_channels, r, r))

    def forward(self, features: Tensor, colours: Tensor | None = None) -> Tensor:
        c = self.coefficients(code_input(features, self.pool, colours))
        # A matrix product, not an einsum: onnxruntime runs its MatMul many times faster than the
        # equivalent Einsum (the same numbers), and the Einsum was a large part of the encoder's time.
        planes = (c @ self.components.flatten(1)).view(c.shape[0], *self.components.shape[1:])
        t = self.triplane_resolution
        if planes.shape[-1] != t:
            planes = F.interpolate(planes, size=(t, t), mode="bilinear", align_corners=False)
        return planes
