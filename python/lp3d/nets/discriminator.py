"""EG3D's dual discriminator and the non-saturating logistic GAN losses.

Paper §3.2: "L_adv is the adversarial loss using a pretrained dual discriminator from EG3D which is
fine-tuned during training", trained to tell renders of the frozen teacher (real) from renders of
the encoder's triplanes (fake) — no real photographs. Structure (EG3D ``DualDiscriminator``)::

    image (B,3,R,R) ⊕ upsample(image_raw (B,3,r,r) -> R) = (B,6,R,R)
      b{R}: fromrgb 1×1 -> resnet block (conv 3×3, conv 3×3 ↓2, skip 1×1 ↓2, each branch · √½)
      b{R/2} … b8: resnet blocks
      b4 (epilogue): minibatch stddev, conv 3×3, fc, out -> logits (B, 1)
      optional camera conditioning: a mapping network embeds the 25-float camera into cmap and the
      logit is the projection <out, cmap>/√cmap_dim (off by default, ``c_dim=0``)

Widths follow StyleGAN2's ``min(channel_base // res, channel_max)``; EG3D uses 32768 / 512 at 512².
Simplifications: fp32 only (no fp16 blocks, no conv_clamp); minibatch-stddev groups use the largest
divisor of the batch not above ``mbstd_group_size`` (EG3D requires divisibility and fails otherwise).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.stylegan_ops import FullyConnectedLayer, bias_lrelu, downsample2d, setup_filter, upfirdn2d

__all__ = [
    "DISCRIMINATOR_CONFIGS",
    "DiscriminatorConfig",
    "DualDiscriminator",
    "build_discriminator",
    "d_loss",
    "g_loss",
    "r1_penalty",
]


@dataclass(frozen=True)
class DiscriminatorConfig:
    """Sizes of the dual discriminator; ``eg3d`` is EG3D's FFHQ-512 discriminator (without c)."""

    name: str = "eg3d"
    #: Side of the (super-resolved) image it judges; image_raw is resized to this.
    resolution: int = 512
    img_channels: int = 3
    channel_base: int = 32768
    channel_max: int = 512
    #: Camera conditioning: 0 = off (default); 25 = EG3D's camera label.
    c_dim: int = 0
    mapping_layers: int = 8
    mbstd_group_size: int = 4
    mbstd_num_channels: int = 1

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        for name in ("resolution", "img_channels", "channel_base", "channel_max", "mbstd_group_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                raise ValueError(f"DiscriminatorConfig.{name} must be a positive int, got {v!r}")
        for name in ("c_dim", "mbstd_num_channels", "mapping_layers"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"DiscriminatorConfig.{name} must be a non-negative int, got {v!r}")
        r = self.resolution
        if r < 8 or r & (r - 1):
            raise ValueError(f"DiscriminatorConfig.resolution must be a power of two >= 8, got {r}")

    def channels(self, res: int) -> int:
        """StyleGAN2's width at resolution ``res``."""
        return min(self.channel_base // res, self.channel_max)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DiscriminatorConfig:
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"DiscriminatorConfig.from_dict: unknown keys {unknown}")
        return cls(**data)


DISCRIMINATOR_CONFIGS: dict[str, DiscriminatorConfig] = {
    "eg3d": DiscriminatorConfig(),
    "small": DiscriminatorConfig(name="small", resolution=128, channel_base=4096, channel_max=128),
    "tiny": DiscriminatorConfig(name="tiny", resolution=128, channel_base=2048, channel_max=64),
}


class Conv2dLayer(nn.Module):
    """StyleGAN2's Conv2dLayer: equalised-lr conv, optional FIR ↓2, bias, lrelu·√2 (or linear).

    (B, cin, H, W) -> (B, cout, H/down, W/down). Downsampling follows EG3D's ``conv2d_resample``: for a
    3×3 kernel FIR-filter (pad 2) then stride-2 conv; for 1×1 FIR-downsample then conv.
    """

    def __init__(
        self,
        cin: int,
        cout: int,
        kernel_size: int,
        *,
        bias: bool = True,
        activation: str = "lrelu",
        down: int = 1,
    ) -> None:
        super().__init__()
        self.activation = activation
        self.down = down
        self.padding = kernel_size // 2
        self.weight_gain = 1.0 / math.sqrt(cin * kernel_size * kernel_size)
        self.register_buffer("resample_filter", setup_filter())
        self.weight = nn.Parameter(torch.randn(cout, cin, kernel_size, kernel_size))
        self.bias = nn.Parameter(torch.zeros(cout)) if bias else None

    def forward(self, x: Tensor, gain: float = 1.0) -> Tensor:
        w = self.weight.to(x.dtype) * self.weight_gain
        if self.down == 1:
            x = F.conv2d(x, w, padding=self.padding)
        elif w.shape[-1] == 1:
            x = F.conv2d(downsample2d(x, self.resample_filter, self.down), w)
        else:
            fw = self.resample_filter.shape[-1]
            p0 = self.padding + (fw - self.down + 1) // 2
            p1 = self.padding + (fw - self.down) // 2
            x = F.conv2d(upfirdn2d(x, self.resample_filter, padding=(p0, p1, p0, p1)), w, stride=self.down)
        if self.activation == "lrelu":
            return bias_lrelu(x, self.bias, gain)
        if self.bias is not None:
            x = x + self.bias.to(x.dtype).reshape(1, -1, 1, 1)
        return x * gain


class DiscriminatorBlock(nn.Module):
    """StyleGAN2's 'resnet' DiscriminatorBlock. (x (B, cin, r, r) or None, img) -> (B, cout, r/2, r/2).

    The first block (cin = 0) reads the image through ``fromrgb``.
    """

    def __init__(self, cin: int, tmp: int, cout: int, img_channels: int) -> None:
        super().__init__()
        self.cin = cin
        if cin == 0:
            self.fromrgb = Conv2dLayer(img_channels, tmp, 1)
        self.conv0 = Conv2dLayer(tmp, tmp, 3)
        self.conv1 = Conv2dLayer(tmp, cout, 3, down=2)
        self.skip = Conv2dLayer(tmp, cout, 1, bias=False, activation="linear", down=2)

    def forward(self, x: Tensor | None, img: Tensor) -> Tensor:
        if self.cin == 0:
            x = self.fromrgb(img)
        assert x is not None
        y = self.skip(x, gain=math.sqrt(0.5))
        x = self.conv1(self.conv0(x), gain=math.sqrt(0.5))
        return y + x


def minibatch_stddev(x: Tensor, group_size: int, num_channels: int) -> Tensor:
    """Append the std over minibatch groups as ``num_channels`` extra channels.

    (B, C, H, W) -> (B, C + num_channels, H, W).
    """
    n, c, h, w = x.shape
    g = max(d for d in range(1, min(group_size, n) + 1) if n % d == 0)
    f = num_channels
    y = x.reshape(g, -1, f, c // f, h, w)
    y = (y - y.mean(dim=0)).square().mean(dim=0)
    y = (y + 1e-8).sqrt().mean(dim=(2, 3, 4)).reshape(-1, f, 1, 1)
    return torch.cat([x, y.repeat(g, 1, h, w)], dim=1)


class MappingNetwork(nn.Module):
    """Camera-conditioning mapping (StyleGAN2 MappingNetwork with z_dim=0). (B, c_dim) -> (B, cmap_dim)."""

    def __init__(self, c_dim: int, cmap_dim: int, num_layers: int, lr_multiplier: float = 0.01) -> None:
        super().__init__()
        self.embed = FullyConnectedLayer(c_dim, cmap_dim)
        self.layers = nn.ModuleList(
            FullyConnectedLayer(cmap_dim, cmap_dim, activation="lrelu", lr_multiplier=lr_multiplier)
            for _ in range(num_layers)
        )

    def forward(self, c: Tensor) -> Tensor:
        x = self.embed(c)
        x = x * (x.square().mean(dim=1, keepdim=True) + 1e-8).rsqrt()  # normalize_2nd_moment
        for layer in self.layers:
            x = layer(x)
        return x


class DiscriminatorEpilogue(nn.Module):
    """StyleGAN2's b4: minibatch std, conv 3×3, fc, out (+ projection onto cmap). (B, C, 4, 4) -> (B, 1)."""

    def __init__(self, cin: int, cmap_dim: int, group_size: int, num_channels: int) -> None:
        super().__init__()
        self.group_size = group_size
        self.num_channels = num_channels
        self.cmap_dim = cmap_dim
        self.conv = Conv2dLayer(cin + num_channels, cin, 3)
        self.fc = FullyConnectedLayer(cin * 16, cin, activation="lrelu")
        self.out = FullyConnectedLayer(cin, cmap_dim if cmap_dim > 0 else 1)

    def forward(self, x: Tensor, cmap: Tensor | None) -> Tensor:
        if self.num_channels > 0:
            x = minibatch_stddev(x, self.group_size, self.num_channels)
        x = self.out(self.fc(self.conv(x).flatten(1)))
        if cmap is not None:
            x = (x * cmap).sum(dim=1, keepdim=True) / math.sqrt(self.cmap_dim)
        return x


class DualDiscriminator(nn.Module):
    """``forward(image (B,3,R,R), image_raw (B,3,r,r), c=None) -> logits (B, 1)``.

    ``image`` is the super-resolved render, ``image_raw`` the raw neural render (first 3 channels of
    the feature image); EG3D upsamples ``image_raw`` to R (bilinear, antialiased) and stacks the two
    so the discriminator also judges consistency between them.
    """

    def __init__(self, config: DiscriminatorConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or DiscriminatorConfig()
        log2 = int(math.log2(cfg.resolution))
        self.block_resolutions = [2**i for i in range(log2, 2, -1)]
        img_channels = 2 * cfg.img_channels  # image ⊕ upsampled image_raw
        for res in self.block_resolutions:
            cin = cfg.channels(res) if res < cfg.resolution else 0
            block = DiscriminatorBlock(cin, cfg.channels(res), cfg.channels(res // 2), img_channels)
            setattr(self, f"b{res}", block)
        cmap_dim = cfg.channels(4) if cfg.c_dim > 0 else 0
        if cfg.c_dim > 0:
            self.mapping = MappingNetwork(cfg.c_dim, cmap_dim, cfg.mapping_layers)
        self.b4 = DiscriminatorEpilogue(
            cfg.channels(4), cmap_dim, cfg.mbstd_group_size, cfg.mbstd_num_channels
        )

    def forward(self, image: Tensor, image_raw: Tensor, c: Tensor | None = None) -> Tensor:
        cfg = self.config
        r = cfg.resolution
        if image.ndim != 4 or tuple(image.shape[1:]) != (cfg.img_channels, r, r):
            raise ValueError(
                f"image must have shape (B, {cfg.img_channels}, {r}, {r}), got {tuple(image.shape)}"
            )
        if image_raw.ndim != 4 or image_raw.shape[:2] != image.shape[:2]:
            raise ValueError(
                f"image_raw must have shape (B, {cfg.img_channels}, r, r) with B = {image.shape[0]}, "
                f"got {tuple(image_raw.shape)}"
            )
        if cfg.c_dim > 0 and (c is None or tuple(c.shape) != (image.shape[0], cfg.c_dim)):
            got = None if c is None else tuple(c.shape)
            raise ValueError(f"camera c must have shape ({image.shape[0]}, {cfg.c_dim}), got {got}")
        raw = F.interpolate(image_raw, size=(r, r), mode="bilinear", align_corners=False, antialias=True)
        img = torch.cat([image, raw], dim=1)
        x: Tensor | None = None
        for res in self.block_resolutions:
            x = getattr(self, f"b{res}")(x, img)
        assert x is not None
        cmap = self.mapping(c) if cfg.c_dim > 0 and c is not None else None
        return self.b4(x, cmap)


def build_discriminator(config: DiscriminatorConfig | str = "eg3d") -> DualDiscriminator:
    """Build from a config or a name in :data:`DISCRIMINATOR_CONFIGS` (``eg3d``, ``small``, ``tiny``)."""
    if isinstance(config, str):
        if config not in DISCRIMINATOR_CONFIGS:
            raise ValueError(
                f"unknown discriminator config {config!r}; choose one of {sorted(DISCRIMINATOR_CONFIGS)}"
            )
        config = DISCRIMINATOR_CONFIGS[config]
    return DualDiscriminator(config)


# --------------------------------------------------------------------------------------------------
# Losses (StyleGAN2 / EG3D ``StyleGAN2Loss``): non-saturating logistic loss with R1 regularisation
# --------------------------------------------------------------------------------------------------


def d_loss(real_logits: Tensor, fake_logits: Tensor) -> Tensor:
    """Discriminator loss, mean of softplus(fake) + softplus(-real). Logits (B, 1) -> scalar.

    In LP3D "real" are the teacher's renders and "fake" the encoder's (paper §3.2).
    """
    return F.softplus(fake_logits).mean() + F.softplus(-real_logits).mean()


def g_loss(fake_logits: Tensor) -> Tensor:
    """Non-saturating generator loss, mean softplus(-fake). Logits (B, 1) -> scalar."""
    return F.softplus(-fake_logits).mean()


def r1_penalty(real_logits: Tensor, real_inputs: Sequence[Tensor]) -> Tensor:
    """R1: per-sample squared gradient norm of the real logits w.r.t. the real inputs -> (B,).

    Pass both discriminator inputs (``image`` and ``image_raw``, created with ``requires_grad_()``) as
    EG3D does; the loss term is ``r1_penalty(...).mean() * (r1_gamma / 2)`` (EG3D FFHQ: gamma = 1).
    The graph is kept (``create_graph=True``) so the penalty can be back-propagated.
    """
    grads = torch.autograd.grad(outputs=real_logits.sum(), inputs=list(real_inputs), create_graph=True)
    return torch.stack([g.square().flatten(1).sum(dim=1) for g in grads]).sum(dim=0)
