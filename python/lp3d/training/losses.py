"""The distillation objective of paper Eq. 5 and the perceptual losses it uses.

    L = L_tri + L_col + L_LPIPS + L_feat + λ1 · L_adv + λ2 · L_cate                      (paper Eq. 5)

* ``L_tri``: L1 between the teacher's triplane T and the encoder's T̄ (:func:`triplane_loss`).
* ``L_col``: L1 between teacher and student images at the raw (neural rendering, e.g. 128²) and the
  high (super-resolved, e.g. 512²) resolution.
* ``L_LPIPS``: a perceptual loss at both resolutions (LPIPS, or a stated weight-free substitute).
* ``L_feat``: L1 between the 32-channel feature images I_f and Ī_f.
* ``L_adv``: the non-saturating loss of the dual discriminator on the student's (high, raw) pair;
  λ1 = 0.1 for reference views and 0.025 for multiview images.
* ``L_cate``: an optional category-specific loss (ArcFace identity for faces in the paper, λ2 = 1;
  off by default here: no ArcFace weights can be fetched). Pass any callable as the hook.

Perceptual losses. LPIPS comes from the ``lpips`` package, whose calibrated linear heads ship inside
the package but whose VGG/AlexNet backbone weights are torchvision's ImageNet checkpoints and are
never downloaded here: :func:`find_lpips_backbone` looks for them on disk (an explicit path, then
torch hub's checkpoint cache) and raises :class:`LPIPSWeightsNotFound` naming the options when they
are missing. The trainer never switches silently: a weight-free loss must be chosen by name
(``ssim-grad``: :class:`SSIMGradientLoss`, or ``none``).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Literal, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.discriminator import g_loss
from lp3d.render.npz_reader import read_torch_file

__all__ = [
    "LPIPS_BACKBONE_FILES",
    "PERCEPTUAL_KINDS",
    "CategoryLoss",
    "DistillationLoss",
    "LPIPSLoss",
    "LPIPSWeightsNotFound",
    "LossWeights",
    "PerceptualLoss",
    "SSIMGradientLoss",
    "ViewRenders",
    "build_perceptual",
    "find_lpips_backbone",
    "l1",
    "normalised_triplane_loss",
    "ssim",
    "triplane_loss",
]

PerceptualKind = Literal["lpips", "ssim-grad", "none"]
#: Perceptual losses selectable by name (``--perceptual``).
PERCEPTUAL_KINDS: tuple[str, ...] = ("lpips", "ssim-grad", "none")
LPIPSNet = Literal["vgg", "alex"]

#: File names of torchvision's ImageNet checkpoints that LPIPS's backbones are built from.
LPIPS_BACKBONE_FILES: dict[str, str] = {"vgg": "vgg16-397923af.pth", "alex": "alexnet-owt-7be5be79.pth"}


# --------------------------------------------------------------------------------------------------
# Weights
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LossWeights:
    """Weights of the terms of Eq. 5; a zero weight skips the term's computation entirely.

    ``adversarial_reference`` / ``adversarial_multiview`` are λ1 (0.1 / 0.025 in the paper);
    ``category`` is λ2. ``depth`` weights an L1 on the depth maps I_D, which the paper renders but
    does not list in Eq. 5, so it is 0 by default.
    """

    triplane: float = 1.0
    color_raw: float = 1.0
    color_high: float = 1.0
    perceptual_raw: float = 1.0
    perceptual_high: float = 1.0
    feature: float = 1.0
    depth: float = 0.0
    adversarial_reference: float = 0.1
    adversarial_multiview: float = 0.025
    category: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise ValueError(f"LossWeights.{f.name} must be a finite number >= 0, got {value!r}")

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LossWeights:
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"LossWeights.from_dict: unknown keys {unknown}")
        return cls(**data)


# --------------------------------------------------------------------------------------------------
# Pixel losses and SSIM
# --------------------------------------------------------------------------------------------------


def _same_shape(name: str, a: Tensor, b: Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{name}: student and teacher shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")


def l1(a: Tensor, b: Tensor, *, name: str = "l1") -> Tensor:
    """Mean absolute difference of two tensors of the same shape -> scalar."""
    _same_shape(name, a, b)
    return (a - b).abs().mean()


def triplane_loss(pred: Tensor, target: Tensor) -> Tensor:
    """L_tri: L1 between triplanes (B, 3, 32, T, T) -> scalar (paper Eq. 5)."""
    return l1(pred, target, name="triplane")


def normalised_triplane_loss(pred: Tensor, target: Tensor, scale: Tensor) -> Tensor:
    """Channel-normalised L_tri (the CPU recipe's regression loss): L1 between triplanes
    (B, 3, C, T, T) with each channel divided by ``scale`` (C,), the spread of that channel over the
    teacher's identities, so channels of small range (shape fields) weigh as much as colour logits."""
    _same_shape("triplane", pred, target)
    if scale.ndim != 1 or scale.shape[0] != pred.shape[2] or not bool((scale > 0).all()):
        raise ValueError(f"scale must be ({pred.shape[2]},) and positive, got {tuple(scale.shape)}")
    return ((pred - target).abs() / scale.reshape(1, 1, -1, 1, 1)).mean()


def _gaussian_window(size: int, sigma: float, *, device: torch.device, dtype: torch.dtype) -> Tensor:
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(a: Tensor, b: Tensor, *, window: int = 11, sigma: float = 1.5, data_range: float = 2.0) -> Tensor:
    """Per-image SSIM (Wang et al. 2004) of images (B, C, H, W) -> (B,).

    Gaussian window ``window`` x ``window`` (sigma 1.5; shrunk to the image for tiny images), valid
    convolution, ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2`` with ``L = data_range`` (2 for [-1, 1]).
    """
    _same_shape("ssim", a, b)
    c = a.shape[1]
    size = min(window, a.shape[-1], a.shape[-2])
    if size % 2 == 0:
        size -= 1
    g = _gaussian_window(size, sigma * size / window, device=a.device, dtype=a.dtype)

    def blur(x: Tensor) -> Tensor:  # separable, per channel, valid
        x = F.conv2d(x, g.reshape(1, 1, 1, -1).expand(c, 1, 1, size), groups=c)
        return F.conv2d(x, g.reshape(1, 1, -1, 1).expand(c, 1, size, 1), groups=c)

    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.flatten(1).mean(dim=1)


# --------------------------------------------------------------------------------------------------
# Perceptual losses
# --------------------------------------------------------------------------------------------------


class PerceptualLoss(Protocol):
    """``loss(a (B, 3, H, W), b (B, 3, H, W)) -> scalar`` on images in [-1, 1]; ``name`` for logs."""

    name: str

    def __call__(self, a: Tensor, b: Tensor) -> Tensor: ...


class SSIMGradientLoss(nn.Module):
    """``ssim-grad``: a weight-free perceptual substitute for LPIPS (not LPIPS; numbers not comparable).

    Over ``scales`` dyadic scales (2x2 average pooling between them), the mean of
    ``(1 - SSIM(a, b)) + L1(∇a, ∇b)`` with forward differences ∇ along x and y. SSIM compares local
    means, contrasts and structure; the gradient term compares edges, which plain L1 blurs — the two
    properties LPIPS is used for in distillation. (B, 3, H, W) x 2 in [-1, 1] -> scalar.
    """

    name = "ssim-grad"

    def __init__(self, scales: int = 3) -> None:
        super().__init__()
        if scales < 1:
            raise ValueError(f"scales must be >= 1, got {scales}")
        self.scales = scales

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        _same_shape("ssim-grad", a, b)
        total = a.new_zeros(())
        n = 0
        for s in range(self.scales):
            if s > 0:
                if min(a.shape[-2:]) < 8:
                    break
                a, b = F.avg_pool2d(a, 2), F.avg_pool2d(b, 2)
            grad = (a.diff(dim=-1) - b.diff(dim=-1)).abs().mean() + (
                a.diff(dim=-2) - b.diff(dim=-2)
            ).abs().mean()
            total = total + (1.0 - ssim(a, b)).mean() + grad
            n += 1
        return total / n


class LPIPSWeightsNotFound(FileNotFoundError):
    """LPIPS's backbone (torchvision ImageNet) weights are not on disk; the message names the options."""


def lpips_backbone_candidates(net: LPIPSNet) -> list[Path]:
    """Where torchvision keeps the checkpoint of LPIPS's backbone ``net``: torch hub's cache
    (``$TORCH_HOME/hub/checkpoints``, default ``~/.cache/torch/hub/checkpoints``)."""
    name = LPIPS_BACKBONE_FILES[net]
    dirs = [
        Path(torch.hub.get_dir()) / "checkpoints",
        Path.home() / ".cache" / "torch" / "hub" / "checkpoints",
    ]
    out: list[Path] = []
    for d in dirs:
        if d / name not in out:
            out.append(d / name)
    return out


def find_lpips_backbone(net: LPIPSNet, explicit: str | os.PathLike[str] | None = None) -> Path:
    """The backbone checkpoint for LPIPS ``net`` ('vgg' or 'alex'), or :class:`LPIPSWeightsNotFound`.

    An explicit path must exist (it is never replaced by a search); otherwise the first existing file
    of :func:`lpips_backbone_candidates` is used.
    """
    if net not in LPIPS_BACKBONE_FILES:
        raise ValueError(f"LPIPS net must be one of {sorted(LPIPS_BACKBONE_FILES)}, got {net!r}")
    if explicit is not None:
        path = Path(explicit)
        if not path.is_file():
            raise LPIPSWeightsNotFound(f"--lpips-weights {str(path)!r}: no such file")
        return path
    candidates = lpips_backbone_candidates(net)
    for path in candidates:
        if path.is_file():
            return path
    searched = "\n".join(f"    {p}" for p in candidates)
    raise LPIPSWeightsNotFound(
        f"LPIPS needs torchvision's ImageNet {net} backbone weights ({LPIPS_BACKBONE_FILES[net]}), which "
        f"are not on disk and are never downloaded. Searched:\n{searched}\n"
        "Options:\n"
        f"  1. supply them: --lpips-weights PATH (a torchvision {net} state dict), or copy the file into "
        "the torch hub checkpoint directory above;\n"
        "  2. choose a weight-free perceptual loss instead: --perceptual ssim-grad (multi-scale SSIM + "
        "image-gradient L1; not LPIPS), or --perceptual none (drop the perceptual term)."
    )


def _backbone_state(path: Path, target: dict[str, Tensor], net: str) -> dict[str, Tensor]:
    """Map a torchvision ``{net}`` state dict (``features.N.*``, or bare ``N.*``) onto lpips's
    ``net.sliceK.N.*`` keys; raise ValueError naming what does not fit."""
    try:
        raw = read_torch_file(path, "LPIPS backbone weights")
    except OSError as e:
        raise ValueError(str(e)) from None
    if not isinstance(raw, dict):
        raise ValueError(f"{str(path)!r} does not hold a state dict (got {type(raw).__name__})")
    out: dict[str, Tensor] = {}
    for key, ref in target.items():
        if not key.startswith("net.slice"):
            continue
        index_and_param = key.split(".", 2)[2]  # "net.slice2.5.weight" -> "5.weight"
        src = raw.get(f"features.{index_and_param}", raw.get(index_and_param))
        if src is None:
            raise ValueError(
                f"{str(path)!r} is not a torchvision {net} checkpoint: missing 'features.{index_and_param}'"
            )
        if tuple(src.shape) != tuple(ref.shape):
            raise ValueError(
                f"{str(path)!r} is not a torchvision {net} checkpoint: 'features.{index_and_param}' has "
                f"shape {tuple(src.shape)}, expected {tuple(ref.shape)}"
            )
        out[key] = src
    return out


class LPIPSLoss(nn.Module):
    """LPIPS (Zhang et al. 2018) from the ``lpips`` package, backbone weights loaded from disk.

    ``forward(a, b)``: images (B, 3, H, W) in [-1, 1] -> mean LPIPS distance (scalar); ``distance``
    gives the per-image values (B,). Frozen (no parameter requires grad), always in eval mode.
    """

    def __init__(self, net: LPIPSNet = "vgg", weights: str | os.PathLike[str] | None = None) -> None:
        super().__init__()
        path = find_lpips_backbone(net, weights)
        try:
            import lpips  # the train extra; imported here so the rest of lp3d does not need it
        except ImportError as e:
            raise ImportError(
                "the LPIPS loss needs the 'lpips' package (pip install 'lp3d[train]'), or choose "
                "--perceptual ssim-grad / none"
            ) from e
        with warnings.catch_warnings(), torch.device("meta"):
            warnings.simplefilter("ignore")  # torchvision's deprecation notes about `pretrained=`
            # Built on the meta device: no download (pnet_rand) and no time spent initialising
            # AlexNet/VGG classifier layers that LPIPS throws away; every weight is loaded below.
            model = lpips.LPIPS(net=net, pretrained=False, pnet_rand=True, verbose=False)
        constants = {k: v.clone() for k, v in model.scaling_layer.state_dict().items()}  # made on the CPU
        model = model.to_empty(device="cpu")
        # The calibrated linear heads ship inside the lpips package (weights/v0.1/<net>.pth).
        heads_path = Path(lpips.__file__).parent / "weights" / "v0.1" / f"{net}.pth"
        heads = torch.load(heads_path, map_location="cpu", weights_only=True)
        state = {f"scaling_layer.{k}": v for k, v in constants.items()}
        for key, value in heads.items():  # "lin3.model.1.weight", also reachable as "lins.3.model.1.weight"
            state[key] = value
            state["lins." + key[3:]] = value
        state.update(_backbone_state(path, model.state_dict(), net))
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as e:
            raise ValueError(f"LPIPS ({net}) weights from {str(path)!r} do not fit: {e}") from None
        model.eval().requires_grad_(False)
        self.model = model
        self.net = net
        self.weights_path = str(path)
        self.name = f"lpips-{net}"

    def train(self, mode: bool = True) -> LPIPSLoss:
        super().train(False)  # dropout in the linear heads must stay off
        return self

    def distance(self, a: Tensor, b: Tensor) -> Tensor:
        """Per-image LPIPS distances (B,)."""
        _same_shape("lpips", a, b)
        return self.model(a, b).flatten()

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        return self.distance(a, b).mean()


def build_perceptual(
    kind: str, *, lpips_net: LPIPSNet = "vgg", lpips_weights: str | os.PathLike[str] | None = None
) -> nn.Module | None:
    """The perceptual loss named ``kind`` (``lpips``, ``ssim-grad`` or ``none`` -> None).

    Raises:
        LPIPSWeightsNotFound: ``lpips`` without backbone weights on disk (never a silent fallback).
    """
    if kind == "lpips":
        return LPIPSLoss(lpips_net, lpips_weights)
    if kind == "ssim-grad":
        return SSIMGradientLoss()
    if kind == "none":
        return None
    raise ValueError(f"unknown perceptual loss {kind!r}; choose one of {list(PERCEPTUAL_KINDS)}")


# --------------------------------------------------------------------------------------------------
# Eq. 5
# --------------------------------------------------------------------------------------------------


#: ``category(student_high (B, 3, R, R), teacher_high (B, 3, R, R)) -> scalar``, e.g. an ArcFace
#: identity loss for faces (paper: λ2 = 1 for FFHQ, 0 for cats).
CategoryLoss = Callable[[Tensor, Tensor], Tensor]


@dataclass
class ViewRenders:
    """The renders of B views (paper §2): ``features`` I_f (B, 32, r, r) in about [-1, 1], ``high``
    I_high (B, 3, R, R) (super-resolved, or the teacher's direct high-resolution render) and ``depth``
    I_D (B, r, r). ``raw`` I_raw is the first three feature channels."""

    features: Tensor
    high: Tensor
    depth: Tensor

    @property
    def raw(self) -> Tensor:
        return self.features[:, :3]


class DistillationLoss:
    """Eq. 5 for one set of views; weights are passed per call (they change with the training stage).

    Args:
        perceptual: the perceptual loss (LPIPS or a named substitute) or None (its weights must be 0).
        category: the optional category-loss hook; required when ``weights.category > 0``.
    """

    def __init__(self, perceptual: PerceptualLoss | nn.Module | None, category: CategoryLoss | None = None):
        self.perceptual = perceptual
        self.category = category

    def triplane(self, pred: Tensor, target: Tensor) -> Tensor:
        return triplane_loss(pred, target)

    def views(
        self,
        student: ViewRenders,
        teacher: ViewRenders,
        weights: LossWeights,
        *,
        kind: Literal["reference", "multiview"],
        discriminator: nn.Module | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Weighted sum of the image terms of Eq. 5 for one view set, and the unweighted terms.

        Returns:
            ``(total, terms)``: a scalar with gradient, and ``{name: detached scalar}`` of every term
            computed (``col_raw``, ``col_high``, ``perc_raw``, ``perc_high``, ``feat``, ``depth``,
            ``adv``, ``cate``); terms with zero weight are not computed.
        """
        if kind not in ("reference", "multiview"):
            raise ValueError(f"kind must be 'reference' or 'multiview', got {kind!r}")
        adv_weight = weights.adversarial_reference if kind == "reference" else weights.adversarial_multiview
        terms: dict[str, Tensor] = {}
        total = student.high.new_zeros(())

        def add(name: str, weight: float, fn: Callable[[], Tensor]) -> None:
            nonlocal total
            if weight > 0:
                value = fn()
                terms[name] = value.detach()
                total = total + weight * value

        add("col_raw", weights.color_raw, lambda: l1(student.raw, teacher.raw, name="col_raw"))
        add("col_high", weights.color_high, lambda: l1(student.high, teacher.high, name="col_high"))
        if weights.perceptual_raw > 0 or weights.perceptual_high > 0:
            if self.perceptual is None:
                raise ValueError("perceptual weights are > 0 but no perceptual loss was given (--perceptual)")
            perc = self.perceptual
            add("perc_raw", weights.perceptual_raw, lambda: perc(student.raw, teacher.raw))
            add("perc_high", weights.perceptual_high, lambda: perc(student.high, teacher.high))
        add("feat", weights.feature, lambda: l1(student.features, teacher.features, name="feat"))
        add("depth", weights.depth, lambda: l1(student.depth, teacher.depth, name="depth"))
        if adv_weight > 0:
            if discriminator is None:
                raise ValueError("adversarial weight > 0 but no discriminator was given")
            add("adv", adv_weight, lambda: g_loss(discriminator(student.high, student.raw)))
        if weights.category > 0:
            if self.category is None:
                raise ValueError("LossWeights.category > 0 but no category loss hook was given")
            cat = self.category
            add("cate", weights.category, lambda: cat(student.high, teacher.high))
        return total, terms
