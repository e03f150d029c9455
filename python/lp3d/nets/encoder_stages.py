"""The three LP3D modules around DeepLabV3 (paper §3.1, Eq. 3-4): :class:`LowEncoder` (E_low),
:class:`HighEncoder` (E_high) and :class:`TriplaneHead`, each sized by an
:class:`~lp3d.nets.encoder_config.EncoderConfig`.

Imports lp3d.nets.encoder_config and lp3d.nets.encoder_blocks.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.encoder_blocks import ViT, conv
from lp3d.nets.encoder_config import EncoderConfig


class Upsample2x(nn.Module):
    """Bilinear ×2 (align_corners=False)."""

    def forward(self, x: Tensor) -> Tensor:
        return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


class LowEncoder(nn.Module):
    """E_low, Eq. 3: F = Conv(ViT(F_low)). (B, aspp, S/8, S/8) -> F (B, feature_channels, R_f, R_f)."""

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        self.vit = ViT(
            cfg.aspp_channels,
            cfg.low_embed_dim,
            cfg.low_depth,
            cfg.low_heads,
            cfg.low_mlp_ratio,
            cfg.low_sr_ratio,
        )
        layers: list[nn.Module] = []
        cin = cfg.low_embed_dim // 4
        for _ in range(cfg.low_upsamples):
            layers += [Upsample2x(), conv(cin, cfg.low_conv_channels, 3), nn.ReLU()]
            cin = cfg.low_conv_channels
        if cfg.low_upsamples == 0:
            layers += [conv(cin, cfg.low_conv_channels, 3), nn.ReLU()]
            cin = cfg.low_conv_channels
        layers.append(conv(cin, cfg.feature_channels, 3))
        self.convs = nn.Sequential(*layers)

    def forward(self, f_low: Tensor) -> Tensor:
        return self.convs(self.vit(f_low))


class HighEncoder(nn.Module):
    """E_high: a shallow CNN with a single downsampling stage (§3.1, Eq. 4).

    full: the image with its coordinates (B, 5, S, S) -> conv7×7 stride 2 -> convs -> (B, C_f, S/2, S/2).
    LT: DeepLabV3's second-layer features (B, w0, S/4, S/4) -> convs -> (B, C_f, S/4, S/4) (supplement).
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        cin = 5 if cfg.high_source == "image" else cfg.backbone_widths[0]
        k = 7 if cfg.high_stride == 2 else 3
        layers: list[nn.Module] = [
            conv(cin, cfg.high_stem_channels, k, stride=cfg.high_stride),
            nn.LeakyReLU(0.01),
        ]
        c = cfg.high_stem_channels
        for _ in range(cfg.high_convs):
            layers += [conv(c, cfg.high_channels, 3), nn.LeakyReLU(0.01)]
            c = cfg.high_channels
        layers.append(conv(c, cfg.feature_channels, 3))
        self.convs = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        return self.convs(x)


class TriplaneHead(nn.Module):
    """Eq. 4: T = Conv(ViT(F ⊕ F_high)), with F skipped into the output convolutions.

    (F, F_high) each (B, C_f, R_f, R_f) -> (B, 3·32, T, T).
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = 2 * cfg.feature_channels
        for c in cfg.head_in_channels:
            layers += [conv(cin, c, 3), nn.LeakyReLU(0.01)]
            cin = c
        self.in_convs = nn.Sequential(*layers)
        self.vit = ViT(
            cin, cfg.head_embed_dim, cfg.head_depth, cfg.head_heads, cfg.head_mlp_ratio, cfg.head_sr_ratio
        )
        # Output convolutions; LT-like configs upsample after the first one to reach the triplane size.
        layers = []
        cin = cfg.head_embed_dim // 4 + cfg.feature_channels
        ups = cfg.head_upsamples
        for c in cfg.head_out_channels:
            layers += [conv(cin, c, 3), nn.LeakyReLU(0.01)]
            if ups > 0:
                layers.append(Upsample2x())
                ups -= 1
            cin = c
        layers += [Upsample2x()] * ups
        layers.append(conv(cin, cfg.out_channels, 3))
        self.out_convs = nn.Sequential(*layers)

    def forward(self, f: Tensor, f_high: Tensor) -> Tensor:
        x = self.vit(self.in_convs(torch.cat([f, f_high], dim=1)))
        return self.out_convs(torch.cat([x, f], dim=1))
