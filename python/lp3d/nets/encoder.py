"""The LP3D triplane encoder E: an unposed portrait image -> an EG3D-format triplane.

Paper §3.1 (Eq. 3-4) and supplement "Implementation details":

    F_low  = DeepLabV3(I ⊕ xy)                ResNet34, 5-channel input, no batch norm
    F      = Conv(ViT(F_low))                  Segformer patch embed + efficient-attention blocks
    F_high = E_high(I ⊕ xy)                    one downsampling stage (LT: DeepLabV3's 2nd-layer features)
    T      = Conv(ViT(Conv(F ⊕ F_high)) ⊕ F)   the triplane (B, 3, 32, T, T)

Everything is written here in plain PyTorch (no segmentation-models-pytorch / timm), so the two
changes the paper makes to DeepLabV3 (5 input channels, batch norm removed with conv biases restored)
are visible in the code rather than patched into a third-party model.

Shapes for the ``full`` configuration (512² input, 256² triplane)::

    image (B,3,512,512) ─► ⊕ xy ─► (B,5,512,512)
      ResNet34 (output stride 8, dilated layer3/4) ─► (B,512,64,64) ─► ASPP ─► F_low (B,256,64,64)
      E_low: patch embed /2 ─► 32² tokens × 1024 ─► 5 blocks ─► pixel shuffle ─► (B,256,64,64)
             ─► [bilinear ×2, conv] × 2 ─► F (B,96,256,256)
      E_high: conv7×7 /2 + convs ─► F_high (B,96,256,256)
      head: F ⊕ F_high ─► convs ─► patch embed /2 ─► 128² tokens × 1024 ─► 1 block (sr 2)
            ─► pixel shuffle (B,256,256,256) ⊕ F ─► convs ─► (B,96,256,256) ─► (B,3,32,256,256)

Interpretations. The supplement gives the layer-by-layer structure of E_low, E_high and the head only
as figures (images, not text), so their widths here follow public re-implementations of those figures:
1024-dim tokens; E_low with 5 blocks (4 heads, MLP ratio 2, no spatial reduction); a head with 1 block
(spatial reduction 2); pixel shuffle ×2 after each ViT; 96-channel F and F_high; ReLU in E_low's convs
and LeakyReLU(0.01) elsewhere. With standard DeepLabV3 (output stride 8, dilated layer3/4, ASPP rates
12/24/36, 256 channels) this gives 87.3M parameters against the paper's 87M. ``lt`` keeps the same
structure with lower-resolution intermediate maps (F, F_high at 128² instead of 256²), 2 E_low blocks,
128-channel features, and E_high fed by ResNet layer1's output (stride 4; the "second layer" when the
stem counts as the first): 62.5M against 63M. The coordinate channels span [-1, 1]. No pretrained
weights are used (see :meth:`LP3DEncoder.reset_parameters`).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "CONFIGS",
    "EncoderConfig",
    "LP3DEncoder",
    "build_encoder",
    "count_parameters",
    "parameter_breakdown",
    "pixel_coordinates",
]

HighSource = Literal["image", "backbone"]


# --------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EncoderConfig:
    """Every size of the encoder; the named configurations are in :data:`CONFIGS`.

    Resolutions (S = ``image_size``): DeepLabV3 works at output stride 8, so ``F_low`` is S/8. E_low's
    patch embedding halves that, pixel shuffle restores it, and bilinear ×2 stages bring ``F`` up to
    ``feature_resolution`` (which must be S/8 · 2^k). ``F_high`` is produced at ``feature_resolution``
    too; the head's patch embedding halves it again and the head's output convolutions upsample (×2
    stages) to ``triplane_resolution`` (which must be ``feature_resolution`` · 2^m).
    """

    name: str = "custom"
    #: Input image side S; the encoder accepts exactly (B, 3, S, S).
    image_size: int = 512
    #: Triplane side T and channels per plane (EG3D: 256, 32).
    triplane_resolution: int = 256
    plane_channels: int = 32
    #: Side of F and F_high (full: 256 = T; LT: 128 = T/2, "lower-resolution intermediate maps").
    feature_resolution: int = 256

    # DeepLabV3 with a ResNet34 encoder (supplement, "Encoder for F_low").
    backbone_widths: tuple[int, int, int, int] = (64, 128, 256, 512)
    backbone_depths: tuple[int, int, int, int] = (3, 4, 6, 3)
    aspp_channels: int = 256
    aspp_rates: tuple[int, int, int] = (12, 24, 36)
    #: segmentation-models-pytorch's ASPP ends with Dropout(0.5); kept for full/lt, 0 for CPU configs.
    aspp_dropout: float = 0.5

    # E_low: Segformer OverlapPatchEmbed (patch 3, stride 2) + efficient self-attention blocks.
    low_embed_dim: int = 1024
    low_depth: int = 5
    low_heads: int = 4
    low_mlp_ratio: float = 2.0
    low_sr_ratio: int = 1
    #: Width of the convolutions after the pixel shuffle, and of F itself.
    low_conv_channels: int = 128
    feature_channels: int = 96

    # E_high: one downsampling stage; "image" (full) or DeepLabV3's second-layer features (LT).
    high_source: HighSource = "image"
    high_stem_channels: int = 64
    high_channels: int = 96
    high_convs: int = 4

    # The head: Conv(ViT(F ⊕ F_high)) with a skip of F into its output convolutions.
    head_in_channels: tuple[int, ...] = (256, 128)
    head_embed_dim: int = 1024
    head_depth: int = 1
    head_heads: int = 2
    head_mlp_ratio: float = 2.0
    head_sr_ratio: int = 2
    head_out_channels: tuple[int, ...] = (256, 128, 128)

    # The plane basis (CPU configurations; not in the paper, 0 turns it off): K coefficients regressed
    # from DeepLab's features select a learned basis of K planes at ``basis_resolution``², added
    # (upsampled) to the head's output. Initialised from the principal components of the teacher's
    # triplanes: they span its identities in ~100 dimensions (python/lp3d/training/__init__.py,
    # "The CPU recipe").
    basis_components: int = 0
    basis_resolution: int = 32
    basis_pool: int = 4
    basis_hidden: int = 512

    def __post_init__(self) -> None:
        self.validate()

    # -- derived sizes -----------------------------------------------------------------------------
    @property
    def low_resolution(self) -> int:
        """Side of F_low (DeepLabV3 output stride 8)."""
        return self.image_size // 8

    @property
    def low_upsamples(self) -> int:
        """Bilinear ×2 stages in E_low after the pixel shuffle."""
        return int(round(math.log2(self.feature_resolution / self.low_resolution)))

    @property
    def head_upsamples(self) -> int:
        """Bilinear ×2 stages in the head's output convolutions."""
        return int(round(math.log2(self.triplane_resolution / self.feature_resolution)))

    @property
    def high_input_resolution(self) -> int:
        """Side of E_high's input: the image (S) or ResNet layer1's output (S/4)."""
        return self.image_size if self.high_source == "image" else self.image_size // 4

    @property
    def high_stride(self) -> int:
        return self.high_input_resolution // self.feature_resolution

    @property
    def out_channels(self) -> int:
        return 3 * self.plane_channels

    def validate(self) -> None:
        """Raise ValueError naming the first inconsistent field."""

        def pos_int(name: str, value: Any) -> None:
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"EncoderConfig.{name} must be a positive int, got {value!r}")

        def pow2_ratio(a: int, b: int) -> bool:
            return a >= b and a % b == 0 and (a // b) & (a // b - 1) == 0

        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("name", "high_source", "low_mlp_ratio", "head_mlp_ratio", "aspp_dropout"):
                continue
            if f.name == "basis_components":  # 0: no plane basis
                if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                    raise ValueError(f"EncoderConfig.basis_components must be an int >= 0, got {value!r}")
                continue
            if isinstance(value, tuple):
                if not value:
                    raise ValueError(f"EncoderConfig.{f.name} must not be empty")
                for v in value:
                    pos_int(f.name, v)
            else:
                pos_int(f.name, value)
        if self.basis_components and not pow2_ratio(self.triplane_resolution, self.basis_resolution):
            raise ValueError(
                f"EncoderConfig.basis_resolution ({self.basis_resolution}) must be the triplane_resolution "
                f"({self.triplane_resolution}) divided by a power of 2"
            )
        if self.basis_components and (self.image_size // 8) % self.basis_pool:
            raise ValueError(
                f"EncoderConfig.basis_pool ({self.basis_pool}) must divide the ASPP's resolution "
                f"({self.image_size // 8})"
            )
        if len(self.backbone_widths) != 4 or len(self.backbone_depths) != 4:
            raise ValueError(
                "EncoderConfig.backbone_widths/backbone_depths must have 4 entries (ResNet34 stages)"
            )
        if len(self.aspp_rates) != 3:
            raise ValueError("EncoderConfig.aspp_rates must have 3 atrous rates")
        if not 0.0 <= self.aspp_dropout < 1.0:
            raise ValueError(f"EncoderConfig.aspp_dropout must be in [0, 1), got {self.aspp_dropout!r}")
        for name in ("low_mlp_ratio", "head_mlp_ratio"):
            if not getattr(self, name) > 0:
                raise ValueError(f"EncoderConfig.{name} must be > 0")
        if self.high_source not in ("image", "backbone"):
            raise ValueError(
                f"EncoderConfig.high_source must be 'image' or 'backbone', got {self.high_source!r}"
            )
        if self.image_size % 16:
            raise ValueError(f"EncoderConfig.image_size must be a multiple of 16, got {self.image_size}")
        if not pow2_ratio(self.feature_resolution, self.low_resolution):
            raise ValueError(
                f"EncoderConfig.feature_resolution ({self.feature_resolution}) must be image_size/8 "
                f"({self.low_resolution}) times a power of two"
            )
        if self.feature_resolution % 2:
            raise ValueError(
                "EncoderConfig.feature_resolution must be even (the head's patch embed halves it)"
            )
        if not pow2_ratio(self.triplane_resolution, self.feature_resolution):
            raise ValueError(
                f"EncoderConfig.triplane_resolution ({self.triplane_resolution}) must be feature_resolution "
                f"({self.feature_resolution}) times a power of two"
            )
        if self.high_input_resolution not in (self.feature_resolution, 2 * self.feature_resolution):
            raise ValueError(
                f"EncoderConfig: E_high has a single downsampling stage, so its input "
                f"({self.high_source}, side {self.high_input_resolution}) must be feature_resolution "
                f"({self.feature_resolution}) or twice it"
            )
        for name, dim, heads in (
            ("low", self.low_embed_dim, self.low_heads),
            ("head", self.head_embed_dim, self.head_heads),
        ):
            if dim % 4:
                raise ValueError(f"EncoderConfig.{name}_embed_dim must be divisible by 4 (pixel shuffle ×2)")
            if dim % heads:
                raise ValueError(
                    f"EncoderConfig.{name}_embed_dim ({dim}) must be divisible by {name}_heads ({heads})"
                )
        if (self.low_resolution // 2) % self.low_sr_ratio:
            raise ValueError("EncoderConfig.low_sr_ratio must divide the E_low token grid side")
        if (self.feature_resolution // 2) % self.head_sr_ratio:
            raise ValueError("EncoderConfig.head_sr_ratio must divide the head token grid side")

    # -- serialisation -----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (tuples become lists)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EncoderConfig:
        """Inverse of :meth:`to_dict`; unknown keys are an error (a checkpoint from another version)."""
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ValueError(f"EncoderConfig.from_dict: unknown keys {unknown}")
        kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()}
        return cls(**kwargs)

    @classmethod
    def named(cls, name: str) -> EncoderConfig:
        """One of :data:`CONFIGS` by name."""
        try:
            return CONFIGS[name]
        except KeyError:
            raise ValueError(f"unknown encoder config {name!r}; choose one of {sorted(CONFIGS)}") from None


#: Paper §3 "Implementation details": "Ours" (87M parameters) and "Ours (LT)" (63M), which differ
#: "in resolution of the intermediate feature maps"; plus two small CPU-trainable configurations.
CONFIGS: dict[str, EncoderConfig] = {
    "full": EncoderConfig(name="full"),
    "lt": EncoderConfig(
        name="lt",
        feature_resolution=128,
        low_depth=2,
        feature_channels=128,
        high_source="backbone",
        high_channels=128,
    ),
    # The first CPU configuration (F and F_high at 64²): the encoder of the paper-recipe
    # ``small-paper`` training configuration, kept as the reference of the training profile.
    "small-paper": EncoderConfig(
        name="small-paper",
        image_size=128,
        triplane_resolution=64,
        feature_resolution=64,
        backbone_widths=(32, 64, 128, 256),
        backbone_depths=(2, 2, 2, 1),
        aspp_channels=128,
        aspp_rates=(6, 12, 18),
        aspp_dropout=0.0,
        low_embed_dim=224,
        low_depth=2,
        low_heads=4,
        low_conv_channels=64,
        feature_channels=64,
        high_stem_channels=32,
        high_channels=64,
        high_convs=3,
        head_in_channels=(128, 64),
        head_embed_dim=256,
        head_depth=1,
        head_heads=2,
        head_out_channels=(128, 64, 64),
    ),
    # CPU-shaped: F and F_high at 32² (LT's layout: F_high from the backbone) and one output
    # convolution pair at the 64² plane size: 1.6-2.3x less CPU per identity for the encoder's
    # forward and backward than 64² features (bench/RESULTS.md, "Training profile").
    "small": EncoderConfig(
        name="small",
        image_size=128,
        triplane_resolution=64,
        feature_resolution=32,
        backbone_widths=(32, 64, 128, 256),
        backbone_depths=(2, 2, 2, 1),
        aspp_channels=128,
        aspp_rates=(6, 12, 18),
        aspp_dropout=0.0,
        low_embed_dim=224,
        low_depth=2,
        low_heads=4,
        low_conv_channels=64,
        feature_channels=96,
        high_source="backbone",
        high_stem_channels=32,
        high_channels=96,
        high_convs=3,
        head_in_channels=(192, 128),
        head_embed_dim=256,
        head_depth=1,
        head_heads=2,
        head_out_channels=(192, 64),
        basis_components=64,
    ),
    "tiny": EncoderConfig(
        name="tiny",
        image_size=128,
        triplane_resolution=64,
        feature_resolution=64,
        backbone_widths=(16, 32, 64, 128),
        backbone_depths=(1, 2, 2, 1),
        aspp_channels=64,
        aspp_rates=(2, 4, 6),
        aspp_dropout=0.0,
        low_embed_dim=128,
        low_depth=1,
        low_heads=2,
        low_conv_channels=48,
        feature_channels=32,
        high_stem_channels=16,
        high_channels=32,
        high_convs=2,
        head_in_channels=(64, 32),
        head_embed_dim=128,
        head_depth=1,
        head_heads=2,
        head_out_channels=(64, 48),
        basis_components=32,
        basis_resolution=16,
        basis_hidden=256,
    ),
}


# --------------------------------------------------------------------------------------------------
# DeepLabV3 with a ResNet34 encoder, batch norm removed (supplement, "Encoder for F_low")
# --------------------------------------------------------------------------------------------------


def pixel_coordinates(batch: int, size: int, *, device: torch.device, dtype: torch.dtype) -> Tensor:
    """The two pixel-coordinate channels appended to the image (supplement, "Encoder for F_low").

    Returns (B, 2, S, S): channel 0 is x (column), channel 1 is y (row), both pixel centres mapped
    linearly to [-1, 1] (first pixel -1, last +1), the same range as the image.
    """
    t = torch.linspace(-1.0, 1.0, size, device=device, dtype=dtype)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([xx, yy]).unsqueeze(0).expand(batch, 2, size, size)


def _conv(cin: int, cout: int, k: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    # Batch norm is removed, so every convolution gets its bias back (supplement).
    return nn.Conv2d(cin, cout, k, stride=stride, padding=dilation * (k // 2), dilation=dilation, bias=True)


class BasicBlock(nn.Module):
    """ResNet34's residual block without batch norm: x + conv(relu(conv(x))), then ReLU.

    (B, cin, H, W) -> (B, cout, H/stride, W/stride).
    """

    def __init__(self, cin: int, cout: int, stride: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = _conv(cin, cout, 3, stride=stride, dilation=dilation)
        self.conv2 = _conv(cout, cout, 3, dilation=dilation)
        self.downsample = _conv(cin, cout, 1, stride=stride) if stride != 1 or cin != cout else None

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        y = self.conv2(F.relu(self.conv1(x)))
        return F.relu(y + identity)


class ResNet34Features(nn.Module):
    """ResNet34 (no batch norm, 5 input channels) as DeepLabV3 uses it: output stride 8.

    As in DeepLabV3, layer3 and layer4 keep stride 1 and dilate their convolutions by 2 and 4.
    forward: (B, 5, S, S) -> (layer1 (B, w0, S/4, S/4), layer4 (B, w3, S/8, S/8)).
    """

    def __init__(self, in_channels: int, widths: tuple[int, ...], depths: tuple[int, ...]) -> None:
        super().__init__()
        self.stem = _conv(in_channels, widths[0], 7, stride=2)
        strides = (1, 2, 1, 1)
        dilations = (1, 1, 2, 4)
        cin = widths[0]
        stages = []
        for width, depth, stride, dilation in zip(widths, depths, strides, dilations, strict=True):
            blocks = [BasicBlock(cin, width, stride, dilation)]
            blocks += [BasicBlock(width, width, 1, dilation) for _ in range(depth - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = width
        self.layer1, self.layer2, self.layer3, self.layer4 = stages

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        x = F.relu(self.stem(x))
        x = F.max_pool2d(x, kernel_size=3, stride=2, padding=1)
        c1 = self.layer1(x)
        x = self.layer4(self.layer3(self.layer2(c1)))
        return c1, x


class ASPP(nn.Module):
    """DeepLabV3's decoder (atrous spatial pyramid pooling + 3×3 conv), batch norm removed.

    Its output is F_low: "the layer before bilinear upsampling and segmentation head" (supplement).
    (B, cin, h, w) -> (B, cout, h, w).
    """

    def __init__(self, cin: int, cout: int, rates: tuple[int, ...], dropout: float) -> None:
        super().__init__()
        self.branches = nn.ModuleList(
            [_conv(cin, cout, 1)] + [_conv(cin, cout, 3, dilation=r) for r in rates]
        )
        self.pool = _conv(cin, cout, 1)
        self.project = _conv(cout * (len(rates) + 2), cout, 1)
        self.dropout = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.conv = _conv(cout, cout, 3)

    def forward(self, x: Tensor) -> Tensor:
        outs = [F.relu(b(x)) for b in self.branches]
        pooled = F.relu(self.pool(x.mean(dim=(2, 3), keepdim=True)))
        outs.append(pooled.expand(-1, -1, x.shape[2], x.shape[3]))
        y = self.dropout(F.relu(self.project(torch.cat(outs, dim=1))))
        return F.relu(self.conv(y))


# --------------------------------------------------------------------------------------------------
# Segformer pieces (supplement, "Encoder for F with Conv Layers")
# --------------------------------------------------------------------------------------------------


class OverlapPatchEmbed(nn.Module):
    """Segformer's overlapping patch embedding: conv (kernel 3, stride 2) then LayerNorm.

    (B, cin, H, W) -> tokens (B, H/2 · W/2, dim), returned with the token grid (H/2, W/2).
    """

    def __init__(self, cin: int, dim: int, patch_size: int = 3, stride: int = 2) -> None:
        super().__init__()
        self.proj = nn.Conv2d(cin, dim, patch_size, stride=stride, padding=patch_size // 2)
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: Tensor) -> tuple[Tensor, int, int]:
        x = self.proj(x)
        h, w = x.shape[2], x.shape[3]
        return self.norm(x.flatten(2).transpose(1, 2)), h, w


class EfficientSelfAttention(nn.Module):
    """Segformer's spatial-reduction attention: keys/values from a grid shrunk by ``sr_ratio``.

    Reducing the key/value grid is what lets the head attend over 128² tokens (paper §3.1: "the
    efficient self-attention mechanism allows the use of high-resolution intermediate feature maps").
    (B, N, dim) -> (B, N, dim).
    """

    def __init__(self, dim: int, heads: int, sr_ratio: int) -> None:
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim, bias=True)  # qkv bias (supplement)
        self.kv = nn.Linear(dim, 2 * dim, bias=True)
        self.proj = nn.Linear(dim, dim)
        self.sr_ratio = sr_ratio
        if sr_ratio > 1:
            self.sr = nn.Conv2d(dim, dim, sr_ratio, stride=sr_ratio)
            self.sr_norm = nn.LayerNorm(dim)

    def forward(self, x: Tensor, h: int, w: int) -> Tensor:
        b, n, c = x.shape
        q = self.q(x).reshape(b, n, self.heads, c // self.heads).transpose(1, 2)
        kv_in = x
        if self.sr_ratio > 1:
            grid = x.transpose(1, 2).reshape(b, c, h, w)
            kv_in = self.sr_norm(self.sr(grid).flatten(2).transpose(1, 2))
        k, v = self.kv(kv_in).reshape(b, -1, 2, self.heads, c // self.heads).permute(2, 0, 3, 1, 4).unbind(0)
        out = F.scaled_dot_product_attention(q, k, v)  # no attention dropout (supplement)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class MixFFN(nn.Module):
    """Segformer's Mix-FFN: Linear -> 3×3 depthwise conv -> GELU -> Linear. (B, N, dim) -> (B, N, dim)."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.dwconv = nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor, h: int, w: int) -> Tensor:
        x = self.fc1(x)
        b, n, c = x.shape
        x = self.dwconv(x.transpose(1, 2).reshape(b, c, h, w)).flatten(2).transpose(1, 2)
        return self.fc2(F.gelu(x))


class TransformerBlock(nn.Module):
    """Segformer's pre-norm block, without dropout or drop-path. (B, N, dim) -> (B, N, dim)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, sr_ratio: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = EfficientSelfAttention(dim, heads, sr_ratio)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = MixFFN(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor, h: int, w: int) -> Tensor:
        x = x + self.attn(self.norm1(x), h, w)
        return x + self.mlp(self.norm2(x), h, w)


class ViT(nn.Module):
    """OverlapPatchEmbed + transformer blocks + pixel shuffle back to the input grid.

    (B, cin, H, W) -> (B, dim/4, H, W): the patch embedding halves the grid, PixelShuffle(2) restores it.
    """

    def __init__(self, cin: int, dim: int, depth: int, heads: int, mlp_ratio: float, sr_ratio: int) -> None:
        super().__init__()
        self.patch_embed = OverlapPatchEmbed(cin, dim)
        self.blocks = nn.ModuleList(TransformerBlock(dim, heads, mlp_ratio, sr_ratio) for _ in range(depth))

    def forward(self, x: Tensor) -> Tensor:
        tokens, h, w = self.patch_embed(x)
        for block in self.blocks:
            tokens = block(tokens, h, w)
        grid = tokens.transpose(1, 2).reshape(x.shape[0], -1, h, w)
        return F.pixel_shuffle(grid, 2)


# --------------------------------------------------------------------------------------------------
# The three LP3D modules around DeepLabV3
# --------------------------------------------------------------------------------------------------


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
            layers += [Upsample2x(), _conv(cin, cfg.low_conv_channels, 3), nn.ReLU()]
            cin = cfg.low_conv_channels
        if cfg.low_upsamples == 0:
            layers += [_conv(cin, cfg.low_conv_channels, 3), nn.ReLU()]
            cin = cfg.low_conv_channels
        layers.append(_conv(cin, cfg.feature_channels, 3))
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
            _conv(cin, cfg.high_stem_channels, k, stride=cfg.high_stride),
            nn.LeakyReLU(0.01),
        ]
        c = cfg.high_stem_channels
        for _ in range(cfg.high_convs):
            layers += [_conv(c, cfg.high_channels, 3), nn.LeakyReLU(0.01)]
            c = cfg.high_channels
        layers.append(_conv(c, cfg.feature_channels, 3))
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
            layers += [_conv(cin, c, 3), nn.LeakyReLU(0.01)]
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
            layers += [_conv(cin, c, 3), nn.LeakyReLU(0.01)]
            if ups > 0:
                layers.append(Upsample2x())
                ups -= 1
            cin = c
        layers += [Upsample2x()] * ups
        layers.append(_conv(cin, cfg.out_channels, 3))
        self.out_convs = nn.Sequential(*layers)

    def forward(self, f: Tensor, f_high: Tensor) -> Tensor:
        x = self.vit(self.in_convs(torch.cat([f, f_high], dim=1)))
        return self.out_convs(torch.cat([x, f], dim=1))


# --------------------------------------------------------------------------------------------------
# The encoder
# --------------------------------------------------------------------------------------------------


def _tracing() -> bool:
    """True under torch.jit.trace, torch.compile or torch.export (no data-dependent Python checks there)."""
    compiler = getattr(torch, "compiler", None)
    return bool(
        torch.jit.is_tracing()
        or (compiler is not None and getattr(compiler, "is_compiling", lambda: False)())
        or (compiler is not None and getattr(compiler, "is_exporting", lambda: False)())
    )


class PlaneBasis(nn.Module):
    """``forward(aspp features (B, C_a, R, R)) -> planes (B, 3·32, T, T)``: Σ_k c_k · component_k.

    The coefficients c (B, K) come from an MLP on the features average-pooled to ``basis_pool``²
    (keeping a coarse layout); ``components`` (K, 3·32, R_b, R_b) is learnt, and bilinearly
    upsampled to T. The last layer starts at zero, so an untrained branch adds nothing.
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        k, r = cfg.basis_components, cfg.basis_resolution
        self.pool = cfg.basis_pool
        self.triplane_resolution = cfg.triplane_resolution
        self.coefficients = nn.Sequential(
            nn.Flatten(),
            nn.Linear(cfg.aspp_channels * cfg.basis_pool**2, cfg.basis_hidden),
            nn.LeakyReLU(0.01),
            nn.Linear(cfg.basis_hidden, k),
        )
        self.components = nn.Parameter(torch.zeros(k, 3 * cfg.plane_channels, r, r))

    def forward(self, features: Tensor) -> Tensor:
        c = self.coefficients(F.adaptive_avg_pool2d(features, self.pool))
        planes = torch.einsum("bk,kchw->bchw", c, self.components)
        t = self.triplane_resolution
        if planes.shape[-1] != t:
            planes = F.interpolate(planes, size=(t, t), mode="bilinear", align_corners=False)
        return planes


class LP3DEncoder(nn.Module):
    """E(I) -> T (paper Eq. 4). ``forward(image (B,3,S,S) in [-1,1]) -> triplane (B,3,32,T,T)``.

    The output is an EG3D triplane: plane p holds output channels p·32 … p·32+31, planes in EG3D order
    (see ``lp3d.render.triplane.PLANE_AXES``). The image is expected in [-1, 1] (EG3D's image range); values
    outside are not rejected (augmentations may overshoot slightly), but NaN/Inf are.
    """

    def __init__(self, config: EncoderConfig) -> None:
        super().__init__()
        self.config = config
        self.backbone = ResNet34Features(5, config.backbone_widths, config.backbone_depths)
        self.aspp = ASPP(
            config.backbone_widths[3], config.aspp_channels, config.aspp_rates, config.aspp_dropout
        )
        self.e_low = LowEncoder(config)
        self.e_high = HighEncoder(config)
        self.head = TriplaneHead(config)
        self.basis = PlaneBasis(config) if config.basis_components > 0 else None
        self.reset_parameters()

    # -- initialisation ----------------------------------------------------------------------------
    @torch.no_grad()
    def reset_parameters(self) -> None:
        """Segformer's init for the transformer/conv parts; He init for ResNet34.

        Without batch norm a He-initialised ResNet doubles its activation variance in every residual
        block (16 blocks: ~2^16), so each block's last conv starts at zero and every block starts as
        the identity (Fixup/SkipInit). No pretrained weights exist for this 5-channel, BN-free net.
        """
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.LayerNorm):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Conv2d):
                fan_out = m.kernel_size[0] * m.kernel_size[1] * m.out_channels // m.groups
                nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / fan_out))
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        for m in self.backbone.modules():
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.conv2.weight)
        if self.basis is not None:
            # The branch starts at zero output but not dead: small random components give the last
            # layer a gradient (training from scratch); the CPU recipe replaces them with principal planes.
            last = self.basis.coefficients[-1]
            assert isinstance(last, nn.Linear)
            nn.init.zeros_(last.weight)
            nn.init.normal_(self.basis.components, 0.0, 0.01)

    # -- forward -----------------------------------------------------------------------------------
    def check_image(self, image: Tensor) -> None:
        """Raise ValueError naming what is wrong with ``image`` (shape, dtype, non-finite values)."""
        s = self.config.image_size
        if not isinstance(image, Tensor):
            raise ValueError(f"image must be a torch.Tensor, got {type(image).__name__}")
        if image.ndim != 4:
            raise ValueError(
                f"image must have shape (B, 3, {s}, {s}), got {tuple(image.shape)} ({image.ndim} dims)"
            )
        if image.shape[1] != 3:
            raise ValueError(
                f"image must have 3 channels (RGB; the encoder appends the 2 coordinate channels itself), "
                f"got {image.shape[1]} channels in shape {tuple(image.shape)}"
            )
        if image.shape[2] != s or image.shape[3] != s:
            raise ValueError(
                f"image size must be {s}x{s} for encoder config {self.config.name!r}, "
                f"got {image.shape[2]}x{image.shape[3]}"
            )
        if image.shape[0] == 0:
            raise ValueError("image batch is empty")
        if not image.is_floating_point():
            raise ValueError(f"image must be a floating-point tensor in [-1, 1], got dtype {image.dtype}")
        if image.device.type == "meta" or _tracing():
            return  # no values to look at / keep exported graphs free of data-dependent checks
        bad = ~torch.isfinite(image).flatten(1).all(dim=1)
        if bool(bad.any()):
            items = bad.nonzero().flatten().tolist()
            raise ValueError(f"image contains NaN or Inf values in batch item(s) {items}")

    def forward(self, image: Tensor) -> Tensor:
        """image (B, 3, S, S) in [-1, 1] -> triplane (B, 3, plane_channels, T, T)."""
        self.check_image(image)
        b = image.shape[0]
        coords = pixel_coordinates(b, self.config.image_size, device=image.device, dtype=image.dtype)
        x = torch.cat([image, coords], dim=1)  # 5-channel input (supplement)
        layer1, deep = self.backbone(x)
        a = self.aspp(deep)
        f = self.e_low(a)
        f_high = self.e_high(x if self.config.high_source == "image" else layer1)
        planes = self.head(f, f_high)
        if self.basis is not None:
            planes = planes + self.basis(a)
        t = self.config.triplane_resolution
        return planes.reshape(b, 3, self.config.plane_channels, t, t)

    # -- helpers -----------------------------------------------------------------------------------
    def transformer_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters of the two ViTs (the paper trains them at half the encoder's learning rate)."""
        yield from self.e_low.vit.parameters()
        yield from self.head.vit.parameters()

    def other_parameters(self) -> Iterator[nn.Parameter]:
        """Every parameter not in :meth:`transformer_parameters`."""
        vit_ids = {id(p) for p in self.transformer_parameters()}
        return (p for p in self.parameters() if id(p) not in vit_ids)


def build_encoder(config: EncoderConfig | str) -> LP3DEncoder:
    """Build an encoder from a config or a name in :data:`CONFIGS` (``full``, ``lt``, ``small``, ``tiny``).

    Weights are randomly initialised; nothing is downloaded. Build under ``with torch.device("meta"):``
    to inspect a large configuration without allocating it.
    """
    if isinstance(config, str):
        config = EncoderConfig.named(config)
    if not isinstance(config, EncoderConfig):
        raise ValueError(f"config must be an EncoderConfig or a config name, got {type(config).__name__}")
    return LP3DEncoder(config)


def count_parameters(module: nn.Module) -> int:
    """Number of parameters (works on the meta device)."""
    return sum(p.numel() for p in module.parameters())


def parameter_breakdown(encoder: LP3DEncoder) -> dict[str, int]:
    """Parameter counts per part, in data-flow order; the values sum to the total."""
    return {
        "backbone (ResNet34, 5-ch, no BN)": count_parameters(encoder.backbone),
        "aspp (DeepLabV3 decoder)": count_parameters(encoder.aspp),
        "e_low.vit (patch embed + blocks)": count_parameters(encoder.e_low.vit),
        "e_low.convs": count_parameters(encoder.e_low.convs),
        "e_high": count_parameters(encoder.e_high),
        "head.in_convs": count_parameters(encoder.head.in_convs),
        "head.vit (patch embed + blocks)": count_parameters(encoder.head.vit),
        "head.out_convs": count_parameters(encoder.head.out_convs),
    }


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lp3d.nets.encoder", description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="full", choices=sorted(CONFIGS), help="named configuration")
    parser.add_argument("--json", action="store_true", help="also print the configuration as JSON")
    parser.add_argument(
        "--shape", action="store_true", help="also run a meta-device forward pass and print shapes"
    )
    args = parser.parse_args(argv)
    cfg = EncoderConfig.named(args.config)
    with torch.device("meta"):  # counting needs no memory
        enc = build_encoder(cfg)
    total = count_parameters(enc)
    print(f"encoder config {cfg.name!r}: {total:,} parameters ({total / 1e6:.2f}M)")
    for part, n in parameter_breakdown(enc).items():
        print(f"  {part:<36} {n:>12,}  {100.0 * n / total:5.1f}%")
    vit = sum(p.numel() for p in enc.transformer_parameters())
    print(f"  {'(of which transformer)':<36} {vit:>12,}  {100.0 * vit / total:5.1f}%")
    print(f"  float32 size: {4 * total / 2**20:.1f} MiB, float16: {2 * total / 2**20:.1f} MiB")
    if args.shape:
        s = cfg.image_size
        out = enc(torch.empty(1, 3, s, s, device="meta"))
        print(f"  image (1, 3, {s}, {s}) -> triplane {tuple(out.shape)}")
    if args.json:
        print(json.dumps(cfg.to_dict(), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
