"""EG3D's super-resolution network (``SuperresolutionHybrid8XDC``) driven by a constant w.

Paper §3 ("We make use of the MLP volume renderer and superresolution architectures from EG3D") and
supplement "Implementation details": "we replaced the latent code W injected to the StyleGAN2-based
super-resolution layer with a constant 1". Structure (``docs/eg3d-rendering.md`` §10)::

    feature image (B,32,128,128), rgb = its first 3 channels
      block0: SynthesisBlock 32 -> 256 at 256² (modulated conv up ×2, modulated conv, ToRGB)
      block1: SynthesisBlock 256 -> 128 at 512² (same)
      image path: img = upsample2d(img, [1,3,3,1]) + torgb(x) in every block, starting from rgb
    -> image (B,3,512,512)

Faithful to EG3D in: parameter and buffer names and shapes (so an EG3D ``superresolution`` state
dict should load with ``strict=False``, only ``w_const`` missing; not yet tried on a real checkpoint),
modulation/demodulation, the transposed-conv-then-FIR ×2 upsampling and its padding, lrelu·√2, ToRGB
without demodulation and its 1/√C style gain, the ``[1,3,3,1]`` image skip, and the
bilinear-antialiased resize of inputs that are not ``input_resolution``.

Simplifications (documented differences):
  * fp32 only: no fp16 layers, hence no fp16 weight pre-normalisation and no ``conv_clamp`` (EG3D
    clamps only its fp16 layers).
  * The modulated convolutions always use the non-fused path (scale input, convolve, scale output);
    mathematically identical to EG3D's fused grouped convolution.
  * Noise defaults to ``noise_mode="none"`` (EG3D's FFHQ ``superresolution_noise_mode``); "const" and
    "random" are available and read the same ``noise_const``/``noise_strength`` tensors.
  * Resolutions and widths are configurable: one SynthesisBlock (×2) per doubling from
    ``input_resolution`` to ``output_resolution`` (e.g. 64 -> 128 for CPU training).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.stylegan_ops import FullyConnectedLayer, bias_lrelu, setup_filter, upfirdn2d, upsample2d

__all__ = [
    "SUPERRES_CONFIGS",
    "FoldedSuperResolution",
    "SuperresConfig",
    "SuperResolution",
    "build_superres",
    "modulated_conv2d",
]

NoiseMode = Literal["none", "const", "random"]


#: Upper bounds of :class:`SuperresConfig`'s sizes (EG3D's own module is 32 channels, 128 -> 512, w 512).
SUPERRES_CAPS = {"in_channels": 256, "input_resolution": 1024, "output_resolution": 4096, "w_dim": 4096}
#: Upper bound of one block's width.
MAX_SUPERRES_WIDTH = 4096


@dataclass(frozen=True)
class SuperresConfig:
    """Sizes of the super-resolution network; ``eg3d`` is EG3D's 128 -> 512 module."""

    name: str = "eg3d"
    #: Channels of the rendered feature image (rgb = the first 3).
    in_channels: int = 32
    input_resolution: int = 128
    output_resolution: int = 512
    #: Output channels of each SynthesisBlock; one block per ×2 step.
    block_channels: tuple[int, ...] = (256, 128)
    w_dim: int = 512
    #: The paper's w is a constant 1 (a buffer); True makes it a learned parameter instead.
    learn_w: bool = False
    #: Register EG3D's noise tensors (unused with noise_mode="none", kept for state-dict parity).
    use_noise: bool = True
    #: Resize mismatched inputs with bilinear antialiasing (EG3D's ``sr_antialias``).
    antialias: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.block_channels, list):  # from JSON or argparse
            object.__setattr__(self, "block_channels", tuple(self.block_channels))
        self.validate()

    @property
    def num_blocks(self) -> int:
        return int(round(math.log2(self.output_resolution / self.input_resolution)))

    def validate(self) -> None:
        # Caps before anything is built from a config read from someone's checkpoint: a claimed
        # 10^6-pixel output would otherwise allocate gigabytes before any shape check.
        for name, cap in SUPERRES_CAPS.items():
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not 0 < v <= cap:
                raise ValueError(f"SuperresConfig.{name} must be an int in [1, {cap}], got {v!r}")
        widths = self.block_channels
        if not isinstance(widths, tuple) or not all(
            isinstance(c, int) and not isinstance(c, bool) and 0 < c <= MAX_SUPERRES_WIDTH for c in widths
        ):
            raise ValueError(
                f"SuperresConfig.block_channels must be ints in [1, {MAX_SUPERRES_WIDTH}], got {widths!r}"
            )
        for name in ("learn_w", "use_noise", "antialias"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"SuperresConfig.{name} must be true or false, got {getattr(self, name)!r}")
        if self.in_channels < 3:
            raise ValueError("SuperresConfig.in_channels must be >= 3 (rgb is the first 3 channels)")
        ratio = self.output_resolution // self.input_resolution
        if self.output_resolution % self.input_resolution or ratio < 2 or ratio & (ratio - 1):
            raise ValueError(
                f"SuperresConfig.output_resolution ({self.output_resolution}) must be input_resolution "
                f"({self.input_resolution}) times a power of two >= 2"
            )
        if len(self.block_channels) != self.num_blocks:
            raise ValueError(
                f"SuperresConfig.block_channels needs {self.num_blocks} positive widths (one per ×2), "
                f"got {self.block_channels!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SuperresConfig:
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"SuperresConfig.from_dict: unknown keys {unknown}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()})


SUPERRES_CONFIGS: dict[str, SuperresConfig] = {
    "eg3d": SuperresConfig(),
    "small": SuperresConfig(
        name="small", input_resolution=64, output_resolution=128, block_channels=(128,), w_dim=128
    ),
    "tiny": SuperresConfig(
        name="tiny", input_resolution=64, output_resolution=128, block_channels=(64,), w_dim=64
    ),
}


def modulated_conv2d(
    x: Tensor,
    weight: Tensor,
    styles: Tensor,
    *,
    up: int = 1,
    padding: int = 0,
    resample_filter: Tensor | None = None,
    demodulate: bool = True,
    noise: Tensor | None = None,
) -> Tensor:
    """StyleGAN2's modulated convolution (non-fused form). x (B, I, H, W), weight (O, I, k, k),
    styles (B or 1, I) -> (B, O, H·up, W·up).

    up=2 is EG3D's ``conv2d_resample`` fast path: transposed conv (stride 2, unflipped weight) then the
    FIR filter with gain 4 and padding ``padding + (fw+1)//2 - (k-1)``, which equals FIR upsampling
    followed by the convolution, including at the borders.
    """
    out_ch, in_ch, kh, kw = weight.shape
    x = x * styles.to(x.dtype).reshape(styles.shape[0], in_ch, 1, 1)
    w = weight.to(x.dtype)
    if up == 1:
        x = F.conv2d(x, w, padding=padding)
    else:
        if resample_filter is None:
            raise ValueError("modulated_conv2d: up > 1 needs a resample_filter")
        fw = resample_filter.shape[-1]
        p0 = padding + (fw + up - 1) // 2 - (kw - 1)
        p1 = padding + (fw - up) // 2 - (kw - up)
        x = F.conv_transpose2d(x, w.transpose(0, 1), stride=up)
        x = upfirdn2d(x, resample_filter, padding=(p0, p1, p0, p1), gain=up * up)
    if demodulate:
        # 1/‖w·s‖ per (sample, output channel): unit-variance outputs for unit-variance inputs.
        wm = w.unsqueeze(0) * styles.to(x.dtype).reshape(styles.shape[0], 1, in_ch, 1, 1)
        dcoefs = (wm.square().sum(dim=(2, 3, 4)) + 1e-8).rsqrt()
        x = x * dcoefs.reshape(styles.shape[0], out_ch, 1, 1)
    if noise is not None:
        x = x + noise.to(x.dtype)
    return x


class SynthesisLayer(nn.Module):
    """EG3D's SynthesisLayer: modulated 3×3 conv (optionally up ×2), noise, bias, lrelu·√2.

    (B, cin, r/up, r/up), w (B or 1, w_dim) -> (B, cout, r, r).
    """

    def __init__(
        self, cin: int, cout: int, w_dim: int, resolution: int, *, up: int = 1, use_noise: bool
    ) -> None:
        super().__init__()
        self.up = up
        self.resolution = resolution
        self.use_noise = use_noise
        self.register_buffer("resample_filter", setup_filter())
        self.affine = FullyConnectedLayer(w_dim, cin, bias_init=1.0)
        self.weight = nn.Parameter(torch.randn(cout, cin, 3, 3))
        if use_noise:
            self.register_buffer("noise_const", torch.randn(resolution, resolution))
            self.noise_strength = nn.Parameter(torch.zeros([]))
        self.bias = nn.Parameter(torch.zeros(cout))

    def forward(self, x: Tensor, w: Tensor, noise_mode: NoiseMode = "none") -> Tensor:
        styles = self.affine(w)
        noise = None
        if self.use_noise and noise_mode == "random":
            shape = (x.shape[0], 1, self.resolution, self.resolution)
            noise = torch.randn(shape, device=x.device, dtype=x.dtype) * self.noise_strength
        elif self.use_noise and noise_mode == "const":
            noise = self.noise_const * self.noise_strength
        x = modulated_conv2d(
            x, self.weight, styles, up=self.up, padding=1, resample_filter=self.resample_filter, noise=noise
        )
        return bias_lrelu(x, self.bias)


class ToRGBLayer(nn.Module):
    """EG3D's ToRGBLayer: modulated 1×1 conv, no demodulation, plus bias. (B, cin, r, r) -> (B, 3, r, r)."""

    def __init__(self, cin: int, w_dim: int, out_channels: int = 3) -> None:
        super().__init__()
        self.affine = FullyConnectedLayer(w_dim, cin, bias_init=1.0)
        self.weight = nn.Parameter(torch.randn(out_channels, cin, 1, 1))
        self.bias = nn.Parameter(torch.zeros(out_channels))
        self.weight_gain = 1.0 / math.sqrt(cin)

    def forward(self, x: Tensor, w: Tensor) -> Tensor:
        styles = self.affine(w) * self.weight_gain
        x = modulated_conv2d(x, self.weight, styles, demodulate=False)
        return x + self.bias.to(x.dtype).reshape(1, -1, 1, 1)


class SynthesisBlock(nn.Module):
    """EG3D's SynthesisBlock ('skip' architecture) with in_channels > 0: conv0 (up ×2), conv1, ToRGB.

    (x (B, cin, r/2, r/2), img (B, 3, r/2, r/2), w) -> (x (B, cout, r, r), img (B, 3, r, r)).
    """

    def __init__(self, cin: int, cout: int, w_dim: int, resolution: int, *, use_noise: bool) -> None:
        super().__init__()
        self.resolution = resolution
        self.register_buffer("resample_filter", setup_filter())
        self.conv0 = SynthesisLayer(cin, cout, w_dim, resolution, up=2, use_noise=use_noise)
        self.conv1 = SynthesisLayer(cout, cout, w_dim, resolution, use_noise=use_noise)
        self.torgb = ToRGBLayer(cout, w_dim)

    def forward(
        self, x: Tensor, img: Tensor, w: Tensor, noise_mode: NoiseMode = "none"
    ) -> tuple[Tensor, Tensor]:
        x = self.conv0(x, w, noise_mode)
        x = self.conv1(x, w, noise_mode)
        img = upsample2d(img, self.resample_filter) + self.torgb(x, w)
        return x, img


class SuperResolution(nn.Module):
    """``forward(feature_image (B, C, R, R)) -> image (B, 3, R_out, R_out)``, EG3D's SR with constant w.

    ``rgb = feature_image[:, :3]`` (the raw neural rendering, paper §2). Inputs that are not
    ``input_resolution`` are first resized (bilinear, antialiased), as EG3D does.
    """

    def __init__(self, config: SuperresConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or SuperresConfig()
        w = torch.ones(config.w_dim)  # "a constant 1" (supplement)
        if config.learn_w:
            self.w_const = nn.Parameter(w)
        else:
            self.register_buffer("w_const", w)
        cin, res = config.in_channels, config.input_resolution
        for i, cout in enumerate(config.block_channels):
            res *= 2
            setattr(
                self, f"block{i}", SynthesisBlock(cin, cout, config.w_dim, res, use_noise=config.use_noise)
            )
            cin = cout

    @property
    def blocks(self) -> list[SynthesisBlock]:
        return [getattr(self, f"block{i}") for i in range(self.config.num_blocks)]

    def forward(self, feature_image: Tensor, *, noise_mode: NoiseMode = "none") -> Tensor:
        """feature_image (B, in_channels, R, R) -> image (B, 3, output_resolution, output_resolution)."""
        cfg = self.config
        if feature_image.ndim != 4 or feature_image.shape[1] != cfg.in_channels:
            raise ValueError(
                f"feature_image must have shape (B, {cfg.in_channels}, R, R), "
                f"got {tuple(feature_image.shape)}"
            )
        if feature_image.shape[2] != feature_image.shape[3]:
            raise ValueError(f"feature_image must be square, got {tuple(feature_image.shape[2:])}")
        if noise_mode not in ("none", "const", "random"):
            raise ValueError(f"noise_mode must be 'none', 'const' or 'random', got {noise_mode!r}")
        x = feature_image
        r = cfg.input_resolution
        if x.shape[-1] != r:
            x = F.interpolate(x, size=(r, r), mode="bilinear", align_corners=False, antialias=cfg.antialias)
        img = x[:, :3]  # EG3D resizes rgb separately with the same filter: identical to slicing after
        w = self.w_const.to(x.dtype).unsqueeze(0)  # (1, w_dim): one style for the whole batch
        for block in self.blocks:
            x, img = block(x, img, w, noise_mode)
        return img


class FoldedSuperResolution(nn.Module):
    """The inference form of a :class:`SuperResolution`: with its constant w, every style and
    demodulation factor is a constant, so each modulated convolution is a plain convolution with the
    weight ``w · style[in] · demod[out]`` folded in once. Same outputs (to float rounding), no
    data-dependent shapes, and only standard ops: this is what ``lp3d export`` writes to ONNX.

    ``forward(features (B, C, R, R)) -> image (B, 3, R_out, R_out)`` with ``R = input_resolution``
    exactly (no resize), ``noise_mode="none"``.
    """

    def __init__(self, sr: SuperResolution) -> None:
        super().__init__()
        w = sr.w_const.detach().float().unsqueeze(0)
        parts: dict[str, list[Tensor]] = {k: [] for k in self._PARTS}
        with torch.no_grad():
            for block in sr.blocks:
                styles = block.torgb.affine(w) * block.torgb.weight_gain
                parts["convs_up"].append(
                    self._fold(block.conv0.weight, block.conv0.affine(w), demodulate=True)
                )
                parts["biases_up"].append(block.conv0.bias.detach().clone())
                parts["convs"].append(self._fold(block.conv1.weight, block.conv1.affine(w), demodulate=True))
                parts["biases"].append(block.conv1.bias.detach().clone())
                parts["rgb_weights"].append(self._fold(block.torgb.weight, styles, demodulate=False))
                parts["rgb_biases"].append(block.torgb.bias.detach().clone())
        self._install(sr.config, parts)

    #: The folded weights, one tensor per block each: ``convs_up`` (O, I, 3, 3) before the ×2 transposed
    #: convolution, ``convs`` (O, O, 3, 3), ``rgb_weights`` (3, O, 1, 1) and their biases (O,), (O,), (3,).
    _PARTS = ("convs_up", "biases_up", "convs", "biases", "rgb_weights", "rgb_biases")

    @classmethod
    def from_tensors(cls, config: SuperresConfig, **parts: list[Tensor]) -> FoldedSuperResolution:
        """The folded network from its weights (:attr:`_PARTS`, as a package's ONNX file holds them:
        :func:`lp3d.nets.superres_onnx.read_superres_onnx`). Raises ValueError when they do not chain
        from ``config.in_channels`` through ``config.block_channels``."""
        if sorted(parts) != sorted(cls._PARTS):
            raise ValueError(f"the folded weights are {cls._PARTS}, got {sorted(parts)}")
        cin = config.in_channels
        for i, c in enumerate(config.block_channels):
            want = {
                "convs_up": (c, cin, 3, 3),
                "biases_up": (c,),
                "convs": (c, c, 3, 3),
                "biases": (c,),
                "rgb_weights": (3, c, 1, 1),
                "rgb_biases": (3,),
            }
            for k, shape in want.items():
                if len(parts[k]) != config.num_blocks or tuple(parts[k][i].shape) != shape:
                    got = tuple(parts[k][i].shape) if i < len(parts[k]) else "missing"
                    raise ValueError(f"block {i}'s {k} should be {shape}, got {got}")
            cin = c
        net = cls.__new__(cls)
        nn.Module.__init__(net)
        net._install(config, parts)
        return net

    def _install(self, config: SuperresConfig, parts: dict[str, list[Tensor]]) -> None:
        self.config = config
        f = setup_filter()
        self.fir_width = f.shape[-1]
        # True convolution with the FIR filter (upfirdn2d flips it), gain 4 for ×2 upsampling.
        fir = (f * 4.0).flip([0, 1])
        for k in self._PARTS:
            setattr(
                self, k, nn.ParameterList([nn.Parameter(t.float(), requires_grad=False) for t in parts[k]])
            )
        self.channels: list[int] = [int(w.shape[0]) for w in parts["convs_up"]]
        # Depthwise FIR kernels with the channel counts baked in (ONNX needs static kernel shapes).
        self.register_buffer("fir_rgb", fir.expand(3, 1, *fir.shape).clone())
        for i, c in enumerate(self.channels):
            self.register_buffer(f"fir_{i}", fir.expand(c, 1, *fir.shape).clone())

    @staticmethod
    def _fold(weight: Tensor, styles: Tensor, *, demodulate: bool) -> Tensor:
        """``weight (O, I, k, k) · styles (1, I)`` (and ``· 1/‖·‖`` per output channel)."""
        wm = weight.detach().float() * styles.reshape(1, -1, 1, 1)
        if demodulate:
            wm = wm * (wm.square().sum(dim=(1, 2, 3), keepdim=True) + 1e-8).rsqrt()
        return wm.contiguous()

    def _fir(self, x: Tensor, kernel: Tensor, pad: tuple[int, int], *, zero_insert: bool) -> Tensor:
        """(B, C, H, W): optionally insert zeros (×2), pad (p0 before, p1 after; negative crops), then
        filter with the depthwise ``kernel`` (C, 1, k, k)."""
        c, h, w = kernel.shape[0], x.shape[2], x.shape[3]
        if zero_insert:
            x = F.pad(x.reshape(-1, c, h, 1, w, 1), [0, 1, 0, 0, 0, 1]).reshape(-1, c, 2 * h, 2 * w)
        p0, p1 = pad
        x = F.pad(x, [max(p0, 0), max(p1, 0), max(p0, 0), max(p1, 0)])
        if p0 < 0 or p1 < 0:
            n = x.shape[-1]
            x = x[:, :, max(-p0, 0) : n - max(-p1, 0), max(-p0, 0) : n - max(-p1, 0)]
        return F.conv2d(x, kernel, groups=c)

    def forward(self, features: Tensor) -> Tensor:
        c, r = self.config.in_channels, self.config.input_resolution
        if features.ndim != 4 or tuple(features.shape[1:]) != (c, r, r):
            raise ValueError(f"features must have shape (B, {c}, {r}, {r}), got {tuple(features.shape)}")
        fw = self.fir_width
        # modulated_conv2d's padding for up=2, a 3×3 kernel and padding 1 (p0, p1 there).
        conv_pad = (1 + (fw + 1) // 2 - 2, 1 + (fw - 2) // 2 - 1)
        skip_pad = ((fw + 1) // 2, (fw - 2) // 2)  # upsample2d's
        x = features
        img = x[:, :3]
        for i in range(len(self.channels)):
            x = F.conv_transpose2d(x, self.convs_up[i].transpose(0, 1), stride=2)
            x = self._fir(x, getattr(self, f"fir_{i}"), conv_pad, zero_insert=False)
            x = bias_lrelu(x, self.biases_up[i])
            x = bias_lrelu(F.conv2d(x, self.convs[i], padding=1), self.biases[i])
            img = self._fir(img, self.fir_rgb, skip_pad, zero_insert=True)
            img = img + F.conv2d(x, self.rgb_weights[i]) + self.rgb_biases[i].reshape(1, -1, 1, 1)
        return img


def build_superres(config: SuperresConfig | str = "eg3d") -> SuperResolution:
    """Build from a config or a name in :data:`SUPERRES_CONFIGS` (``eg3d``, ``small``, ``tiny``)."""
    if isinstance(config, str):
        if config not in SUPERRES_CONFIGS:
            raise ValueError(f"unknown superres config {config!r}; choose one of {sorted(SUPERRES_CONFIGS)}")
        config = SUPERRES_CONFIGS[config]
    return SuperResolution(config)
