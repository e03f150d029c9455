"""The encoder's building blocks, written in plain PyTorch: DeepLabV3 with a ResNet34 encoder and batch
norm removed (:class:`ResNet34Features`, :class:`ASPP`), and Segformer's pieces (:class:`ViT`: an
overlapping patch embedding, efficient self-attention blocks, pixel shuffle). :mod:`lp3d.nets.encoder`
assembles them into the LP3D encoder.

Imports torch only.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# --------------------------------------------------------------------------------------------------
# DeepLabV3 with a ResNet34 encoder, batch norm removed (supplement, "Encoder for F_low")
# --------------------------------------------------------------------------------------------------


def conv(cin: int, cout: int, k: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    """A k x k convolution padded to keep the size (at stride 1), with a bias: batch norm is removed,
    so every convolution gets its bias back (supplement)."""
    return nn.Conv2d(cin, cout, k, stride=stride, padding=dilation * (k // 2), dilation=dilation, bias=True)


class BasicBlock(nn.Module):
    """ResNet34's residual block without batch norm: x + conv(relu(conv(x))), then ReLU.

    (B, cin, H, W) -> (B, cout, H/stride, W/stride).
    """

    def __init__(self, cin: int, cout: int, stride: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = conv(cin, cout, 3, stride=stride, dilation=dilation)
        self.conv2 = conv(cout, cout, 3, dilation=dilation)
        self.downsample = conv(cin, cout, 1, stride=stride) if stride != 1 or cin != cout else None

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
        self.stem = conv(in_channels, widths[0], 7, stride=2)
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
        self.branches = nn.ModuleList([conv(cin, cout, 1)] + [conv(cin, cout, 3, dilation=r) for r in rates])
        self.pool = conv(cin, cout, 1)
        self.project = conv(cout * (len(rates) + 2), cout, 1)
        self.dropout = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.conv = conv(cout, cout, 3)

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
