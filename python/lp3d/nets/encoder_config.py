"""The encoder's configuration: :class:`EncoderConfig` (every size of the LP3D encoder, checked when
made) and the named configurations :data:`CONFIGS` (``full``, ``lt`` and the CPU-trainable ``small``,
``small-paper``, ``tiny``). See :mod:`lp3d.nets.encoder` for the architecture these sizes describe.

Plain data: imports nothing from lp3d (and no torch).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Literal

__all__ = ["CONFIGS", "EncoderConfig", "HighSource"]

HighSource = Literal["image", "backbone"]


def _pos_int(name: str, value: Any) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
        raise ValueError(f"EncoderConfig.{name} must be a positive int, got {value!r}")


def _pow2_ratio(a: int, b: int) -> bool:
    return a >= b and a % b == 0 and (a // b) & (a // b - 1) == 0


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
    # The plane generator (CPU configurations; not in the paper; empty turns it off): a code of
    # ``generator_code`` numbers from the same pooled features, decoded by upsampling convolutions of
    # these widths (the first at T / 2^(n-1), the last at T) into per-texel planes added to the
    # head's output (see lp3d.nets.plane_generator for why).
    generator_channels: tuple[int, ...] = ()
    generator_code: int = 256
    # The input's mean colours on a ``colour_pool``² grid, fed to the basis's and the generator's
    # codes beside the pooled features (CPU configurations; 0 turns it off). Why: the deep features
    # keep a part's luminance but lose its hue (bench/part_probe.py: the shipped small model follows
    # a shirt's hue with gain 0.13), and a grid of mean colours holds each part's hue linearly.
    colour_pool: int = 0

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
    def code_inputs(self) -> int:
        """Inputs of the basis's and the generator's code MLPs: the pooled features, then the colour grid."""
        return self.aspp_channels * self.basis_pool**2 + 3 * self.colour_pool**2

    @property
    def out_channels(self) -> int:
        return 3 * self.plane_channels

    def validate(self) -> None:
        """Raise ValueError naming the first inconsistent field."""
        self._validate_field_types()
        self._validate_basis()
        self._validate_parts()
        self._validate_resolutions()
        self._validate_transformers()

    def _validate_field_types(self) -> None:
        """Every size a positive int (tuples: non-empty, of positive ints); ``basis_components`` >= 0."""
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("name", "high_source", "low_mlp_ratio", "head_mlp_ratio", "aspp_dropout"):
                continue
            if f.name == "generator_channels" and value == ():  # no plane generator
                continue
            if f.name in ("basis_components", "colour_pool"):  # 0: no plane basis / no colour grid
                if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                    raise ValueError(f"EncoderConfig.{f.name} must be an int >= 0, got {value!r}")
                continue
            if isinstance(value, tuple):
                if not value:
                    raise ValueError(f"EncoderConfig.{f.name} must not be empty")
                for v in value:
                    _pos_int(f.name, v)
            else:
                _pos_int(f.name, value)

    def _validate_basis(self) -> None:
        if self.basis_components and not _pow2_ratio(self.triplane_resolution, self.basis_resolution):
            raise ValueError(
                f"EncoderConfig.basis_resolution ({self.basis_resolution}) must be the triplane_resolution "
                f"({self.triplane_resolution}) divided by a power of 2"
            )
        uses_pool = self.basis_components or self.generator_channels
        if uses_pool and (self.image_size // 8) % self.basis_pool:
            raise ValueError(
                f"EncoderConfig.basis_pool ({self.basis_pool}) must divide the ASPP's resolution "
                f"({self.image_size // 8})"
            )
        if self.colour_pool and not uses_pool:
            raise ValueError(
                "EncoderConfig.colour_pool feeds the basis and the generator: it needs one of them"
            )
        if self.colour_pool and self.image_size % self.colour_pool:
            raise ValueError(
                f"EncoderConfig.colour_pool ({self.colour_pool}) must divide the image_size "
                f"({self.image_size})"
            )
        n = len(self.generator_channels)
        if n and (
            n < 2 or self.triplane_resolution % (1 << (n - 1)) or self.triplane_resolution >> (n - 1) < 2
        ):
            raise ValueError(
                f"EncoderConfig.generator_channels ({self.generator_channels}) must have 2 or more widths, "
                f"one per ×2 stage ending at triplane_resolution ({self.triplane_resolution}), the first at "
                "a side of 2 or more"
            )

    def _validate_parts(self) -> None:
        """DeepLabV3's shape, the MLP ratios and E_high's source."""
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

    def _validate_resolutions(self) -> None:
        """The image, F, F_high and triplane sides fit together (see the class docstring)."""
        if self.image_size % 16:
            raise ValueError(f"EncoderConfig.image_size must be a multiple of 16, got {self.image_size}")
        if not _pow2_ratio(self.feature_resolution, self.low_resolution):
            raise ValueError(
                f"EncoderConfig.feature_resolution ({self.feature_resolution}) must be image_size/8 "
                f"({self.low_resolution}) times a power of two"
            )
        if self.feature_resolution % 2:
            raise ValueError(
                "EncoderConfig.feature_resolution must be even (the head's patch embed halves it)"
            )
        if not _pow2_ratio(self.triplane_resolution, self.feature_resolution):
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

    def _validate_transformers(self) -> None:
        """The two ViTs: embed dims divisible by 4 and by the heads, spatial reduction dividing the grid."""
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
    # convolution pair at the 64² plane size: less CPU per identity for the encoder's forward and
    # backward than 64² features (bench/history/RESULTS.md, "Training profile").
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
        generator_channels=(128, 128, 128, 96, 64),
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
        generator_channels=(64, 48, 48, 32, 32),
        generator_code=128,
    ),
}
# ``small`` with a plane basis and no generator: the generator's ablation.
CONFIGS["small-basis"] = replace(CONFIGS["small"], name="small-basis", generator_channels=())
# ``small`` and ``tiny`` with the input's mean colours on an 8² grid beside the pooled features (each
# cell 16² pixels: the shirt fills the bottom row or two); ``small-colour`` is the shipped model's.
CONFIGS["small-colour"] = replace(CONFIGS["small"], name="small-colour", colour_pool=8)
CONFIGS["tiny-colour"] = replace(CONFIGS["tiny"], name="tiny-colour", colour_pool=8)
