"""StyleGAN2/EG3D building blocks shared by the super-resolution network and the discriminator.

Pure-PyTorch versions of what EG3D takes from ``torch_utils.ops`` (``upfirdn2d``, ``bias_act``,
``conv2d_resample``) and ``networks_stylegan2`` (``FullyConnectedLayer``, equalised learning rate):
same semantics and padding arithmetic, no custom CUDA kernels, fp32 only (no fp16 pre-normalisation
or ``conv_clamp``, which EG3D uses only on its fp16 layers).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "FullyConnectedLayer",
    "downsample2d",
    "bias_lrelu",
    "setup_filter",
    "upfirdn2d",
    "upsample2d",
]

#: StyleGAN2's leaky ReLU slope and its gain (variance preserving).
LRELU_ALPHA = 0.2
LRELU_GAIN = math.sqrt(2.0)


def setup_filter(taps: Sequence[float] = (1, 3, 3, 1)) -> Tensor:
    """A separable 2D FIR filter from 1D taps, normalised to sum 1: (k, k) float32."""
    f = torch.as_tensor(list(taps), dtype=torch.float32)
    f = torch.outer(f, f)
    return f / f.sum()


def upfirdn2d(
    x: Tensor,
    f: Tensor,
    *,
    up: int = 1,
    down: int = 1,
    padding: Sequence[int] = (0, 0, 0, 0),
    gain: float = 1.0,
) -> Tensor:
    """Upsample (zero insertion), pad, FIR-filter, downsample: (B, C, H, W) -> (B, C, H', W').

    ``padding`` is (x0, x1, y0, y1), applied after upsampling; negative values crop. The filter is
    applied as a true convolution (flipped), like EG3D's ``upfirdn2d`` with ``flip_filter=False``.
    """
    b, c, h, w = x.shape
    if up > 1:
        x = x.reshape(b, c, h, 1, w, 1)
        x = F.pad(x, [0, up - 1, 0, 0, 0, up - 1])
        x = x.reshape(b, c, h * up, w * up)
    px0, px1, py0, py1 = padding
    x = F.pad(x, [max(px0, 0), max(px1, 0), max(py0, 0), max(py1, 0)])
    x = x[:, :, max(-py0, 0) : x.shape[2] - max(-py1, 0), max(-px0, 0) : x.shape[3] - max(-px1, 0)]
    kernel = (f * gain).to(dtype=x.dtype, device=x.device).flip([0, 1])
    x = F.conv2d(x, kernel[None, None].expand(c, 1, *kernel.shape), groups=c)
    return x[:, :, ::down, ::down] if down > 1 else x


def upsample2d(x: Tensor, f: Tensor, up: int = 2) -> Tensor:
    """FIR upsampling by ``up`` (gain up² keeps the mean): (B, C, H, W) -> (B, C, H·up, W·up)."""
    fw = f.shape[-1]
    p0, p1 = (fw + up - 1) // 2, (fw - up) // 2
    return upfirdn2d(x, f, up=up, padding=(p0, p1, p0, p1), gain=up * up)


def downsample2d(x: Tensor, f: Tensor, down: int = 2) -> Tensor:
    """FIR downsampling by ``down``: (B, C, H, W) -> (B, C, H/down, W/down)."""
    fw = f.shape[-1]
    p0, p1 = (fw - down + 1) // 2, (fw - down) // 2
    return upfirdn2d(x, f, down=down, padding=(p0, p1, p0, p1))


def bias_lrelu(x: Tensor, bias: Tensor | None = None, gain: float = 1.0) -> Tensor:
    """EG3D's ``bias_act(act='lrelu')``: leaky_relu(x + b, 0.2) · √2 · gain. Bias is per channel (dim 1)."""
    if bias is not None:
        x = x + bias.to(x.dtype).reshape([1, -1] + [1] * (x.ndim - 2))
    return F.leaky_relu(x, LRELU_ALPHA) * (LRELU_GAIN * gain)


class FullyConnectedLayer(nn.Module):
    """StyleGAN2's equalised-learning-rate linear layer. (B, in) -> (B, out).

    Weights are stored as N(0, 1)/lr_multiplier and scaled by lr_multiplier/√in at run time, so the
    effective learning rate is the same for every layer (parameter names match EG3D's).
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        *,
        bias: bool = True,
        bias_init: float = 0.0,
        lr_multiplier: float = 1.0,
        activation: str = "linear",
    ) -> None:
        super().__init__()
        if activation not in ("linear", "lrelu"):
            raise ValueError(f"activation must be 'linear' or 'lrelu', got {activation!r}")
        self.in_features = in_features
        self.out_features = out_features
        self.activation = activation
        self.weight = nn.Parameter(torch.randn(out_features, in_features) / lr_multiplier)
        self.bias = nn.Parameter(torch.full((out_features,), float(bias_init))) if bias else None
        self.weight_gain = lr_multiplier / math.sqrt(in_features)
        self.bias_gain = lr_multiplier

    def forward(self, x: Tensor) -> Tensor:
        w = self.weight.to(x.dtype) * self.weight_gain
        b = None if self.bias is None else self.bias.to(x.dtype) * self.bias_gain
        if self.activation == "linear":
            return F.linear(x, w, b)
        return bias_lrelu(F.linear(x, w), b)

    def extra_repr(self) -> str:
        return (
            f"in_features={self.in_features}, out_features={self.out_features}, activation={self.activation}"
        )
