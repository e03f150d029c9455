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

This module assembles the encoder (:class:`LP3DEncoder`, :func:`build_encoder`, ``python -m
lp3d.nets.encoder --config NAME`` to count its parameters) from :mod:`~lp3d.nets.encoder_config`
(:class:`EncoderConfig`, :data:`CONFIGS`, re-exported here), :mod:`~lp3d.nets.encoder_blocks`
(DeepLabV3 and Segformer pieces), :mod:`~lp3d.nets.encoder_stages` (E_low, E_high, the head) and
:mod:`~lp3d.nets.plane_basis` and :mod:`~lp3d.nets.plane_generator`.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.encoder_blocks import ASPP, BasicBlock, ResNet34Features
from lp3d.nets.encoder_config import CONFIGS, EncoderConfig
from lp3d.nets.encoder_stages import HighEncoder, LowEncoder, TriplaneHead
from lp3d.nets.plane_basis import PlaneBasis
from lp3d.nets.plane_generator import PlaneGenerator

__all__ = [
    "CONFIGS",
    "EncoderConfig",
    "LP3DEncoder",
    "build_encoder",
    "count_parameters",
    "parameter_breakdown",
    "pixel_coordinates",
]


def pixel_coordinates(batch: int, size: int, *, device: torch.device, dtype: torch.dtype) -> Tensor:
    """The two pixel-coordinate channels appended to the image (supplement, "Encoder for F_low").

    Returns (B, 2, S, S): channel 0 is x (column), channel 1 is y (row), both pixel centres mapped
    linearly to [-1, 1] (first pixel -1, last +1), the same range as the image.
    """
    t = torch.linspace(-1.0, 1.0, size, device=device, dtype=dtype)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([xx, yy]).unsqueeze(0).expand(batch, 2, size, size)


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
        self.generator = PlaneGenerator(config) if config.generator_channels else None
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
        if self.generator is not None:
            nn.init.zeros_(self.generator.to_planes.weight)
            nn.init.zeros_(self.generator.to_planes.bias)

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
        p = self.config.colour_pool
        colours = F.adaptive_avg_pool2d(image, p) if p else None
        if self.basis is not None:
            planes = planes + self.basis(a, colours)
        if self.generator is not None:
            planes = planes + self.generator(a, colours)
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
        **({"basis": count_parameters(encoder.basis)} if encoder.basis is not None else {}),
        **({"generator": count_parameters(encoder.generator)} if encoder.generator is not None else {}),
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
