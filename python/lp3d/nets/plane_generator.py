"""The plane generator (:class:`PlaneGenerator`, CPU configurations; not in the paper): a small
convolutional decoder from a global code of the image to per-texel planes, added to the head's output.

Why it exists: the plane basis (:mod:`lp3d.nets.plane_basis`) is linear, so it can fade a part in or
out but cannot move an edge; the head's convolutions see the image's layout, which matches only the
front-facing plane. The teacher's planes are a nonlinear function of a few dozen identity parameters,
which is what a generator (a code decoded by upsampling convolutions, as in DCGAN/StyleGAN) expresses:
each texel of each plane is computed, and edges can move with the code.

Imports lp3d.nets.encoder_config and lp3d.nets.plane_basis.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.encoder_config import EncoderConfig
from lp3d.nets.plane_basis import code_input


class PlaneGenerator(nn.Module):
    """``forward(aspp features (B, C_a, R, R), colours (B, 3, P, P) | None) -> planes (B, 3·32, T, T)``.

    The code (B, ``generator_code``) comes from an MLP on the features average-pooled to
    ``basis_pool``² and the input's colour grid, if any (:func:`lp3d.nets.plane_basis.code_input`);
    a linear layer lays it out as ``generator_channels[0]`` maps of side T / 2^(n-1); each further
    width is one stage of bilinear ×2 and a 3×3 convolution; a 1×1 convolution gives the 3·32 plane
    channels. That last layer starts at zero, so an untrained
    generator adds nothing.
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        widths = cfg.generator_channels
        self.pool = cfg.basis_pool
        self.start = cfg.triplane_resolution >> (len(widths) - 1)
        self.code = nn.Sequential(
            nn.Flatten(),  # a no-op on the flat code input, kept so saved weights keep their names
            nn.Linear(cfg.code_inputs, cfg.generator_code),
            nn.LeakyReLU(0.2),
            nn.Linear(cfg.generator_code, widths[0] * self.start**2),
            nn.LeakyReLU(0.2),
        )
        self.stages = nn.ModuleList(
            nn.Conv2d(c_in, c_out, 3, padding=1) for c_in, c_out in zip(widths[:-1], widths[1:], strict=True)
        )
        self.to_planes = nn.Conv2d(widths[-1], cfg.out_channels, 1)

    def forward(self, features: Tensor, colours: Tensor | None = None) -> Tensor:
        x = self.code(code_input(features, self.pool, colours))
        x = x.reshape(x.shape[0], -1, self.start, self.start)
        for conv in self.stages:
            x = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)
            x = F.leaky_relu(conv(x), 0.2)
        return self.to_planes(x)
