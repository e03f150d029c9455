"""The distillation objective (paper Eq. 5) and its perceptual losses."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from lp3d.training.losses import (
    LPIPS_BACKBONE_FILES,
    DistillationLoss,
    LossWeights,
    LPIPSLoss,
    LPIPSWeightsNotFound,
    SSIMGradientLoss,
    ViewRenders,
    build_perceptual,
    find_lpips_backbone,
    ssim,
    triplane_loss,
)


def _views(seed: int, b: int = 2, r: int = 16, s: int = 32) -> ViewRenders:
    g = torch.Generator().manual_seed(seed)
    return ViewRenders(
        features=torch.rand(b, 32, r, r, generator=g) * 2 - 1,
        high=torch.rand(b, 3, s, s, generator=g) * 2 - 1,
        depth=2.5 + torch.rand(b, r, r, generator=g),
    )


class ConstantLogits(nn.Module):
    """A stand-in discriminator: logits = mean of the image minus ``offset``, so g_loss is known."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def forward(self, image: torch.Tensor, image_raw: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        return image.mean(dim=(1, 2, 3)).unsqueeze(1) + 0 * image_raw.mean()


@pytest.fixture
def no_hub(tmp_path, monkeypatch):
    """An empty torch hub cache and home, so no LPIPS backbone can be found by search."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    return tmp_path


def test_triplane_and_pixel_terms_are_hand_checkable():
    a = torch.zeros(1, 3, 32, 4, 4)
    b = torch.full((1, 3, 32, 4, 4), 0.25)
    assert float(triplane_loss(a, b)) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="shapes differ"):
        triplane_loss(a, b[..., :2])

    s, t = _views(0), _views(1)
    w = LossWeights(perceptual_raw=0, perceptual_high=0, adversarial_multiview=0, adversarial_reference=0)
    total, terms = DistillationLoss(None).views(s, t, w, kind="multiview")
    expect = {
        "col_raw": (s.features[:, :3] - t.features[:, :3]).abs().mean(),
        "col_high": (s.high - t.high).abs().mean(),
        "feat": (s.features - t.features).abs().mean(),
    }
    assert set(terms) == set(expect)  # depth (weight 0) and the rest are not computed
    for k, v in expect.items():
        assert float(terms[k]) == pytest.approx(float(v), rel=1e-6)
    assert float(total) == pytest.approx(float(sum(expect.values())), rel=1e-6)

    w2 = LossWeights(
        color_raw=2.0,
        color_high=0.0,
        feature=0.5,
        depth=3.0,
        perceptual_raw=0,
        perceptual_high=0,
        adversarial_multiview=0,
    )
    total2, terms2 = DistillationLoss(None).views(s, t, w2, kind="multiview")
    depth = (s.depth - t.depth).abs().mean()
    assert set(terms2) == {"col_raw", "feat", "depth"}
    assert float(total2) == pytest.approx(
        float(2 * expect["col_raw"] + 0.5 * expect["feat"] + 3 * depth), rel=1e-6
    )


def test_adversarial_weight_is_lambda1_per_view_kind():
    s, t = _views(2), _views(3)
    base = LossWeights(color_raw=0, color_high=0, perceptual_raw=0, perceptual_high=0, feature=0)
    disc = ConstantLogits()
    expected_g = float(F.softplus(-s.high.mean(dim=(1, 2, 3))).mean())
    loss = DistillationLoss(None)
    ref_total, ref_terms = loss.views(s, t, base, kind="reference", discriminator=disc)
    mv_total, mv_terms = loss.views(s, t, base, kind="multiview", discriminator=disc)
    assert float(ref_terms["adv"]) == pytest.approx(expected_g, rel=1e-6)
    assert float(ref_total) == pytest.approx(0.1 * expected_g, rel=1e-6)  # λ1 = 0.1 for the reference view
    assert float(mv_total) == pytest.approx(0.025 * expected_g, rel=1e-6)  # λ1 = 0.025 for multiview
    assert disc.calls == 2
    with pytest.raises(ValueError, match="no discriminator"):
        loss.views(s, t, base, kind="reference")
    with pytest.raises(ValueError, match="kind must be"):
        loss.views(s, t, base, kind="side", discriminator=disc)  # type: ignore[arg-type]


def test_category_hook_is_off_by_default_and_used_when_weighted():
    s, t = _views(4), _views(5)
    assert LossWeights().category == 0.0
    w = LossWeights(
        color_raw=0, color_high=0, perceptual_raw=0, perceptual_high=0, feature=0, adversarial_multiview=0
    )
    seen = []

    def identity_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        seen.append((a.shape, b.shape))
        return (a - b).square().mean()

    total, terms = DistillationLoss(None, identity_loss).views(s, t, w, kind="multiview")
    assert terms == {} and float(total) == 0.0 and not seen  # weight 0: the hook is not even called
    w2 = dataclasses.replace(w, category=1.0)
    total, terms = DistillationLoss(None, identity_loss).views(s, t, w2, kind="multiview")
    assert seen == [(s.high.shape, t.high.shape)]
    assert float(total) == pytest.approx(float((s.high - t.high).square().mean()), rel=1e-6)
    with pytest.raises(ValueError, match="no category loss hook"):
        DistillationLoss(None).views(s, t, w2, kind="multiview")


def test_perceptual_weights_need_a_perceptual_loss():
    with pytest.raises(ValueError, match="no perceptual loss"):
        DistillationLoss(None).views(
            _views(0), _views(1), LossWeights(adversarial_multiview=0), kind="multiview"
        )


def test_loss_weights_validate_and_round_trip():
    with pytest.raises(ValueError, match="triplane"):
        LossWeights(triplane=-1.0)
    with pytest.raises(ValueError, match="feature"):
        LossWeights(feature=math.nan)
    w = LossWeights(triplane=0.01, feature=0.0)
    assert LossWeights.from_dict(w.to_dict()) == w
    with pytest.raises(ValueError, match="unknown keys"):
        LossWeights.from_dict({"lpips": 1.0})


def test_ssim_and_the_weight_free_perceptual_loss():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 32, 32, generator=g) * 2 - 1
    assert torch.allclose(ssim(x, x), torch.ones(2), atol=1e-5)
    noisy = x + 0.2 * torch.randn(x.shape, generator=g)
    very = x + 0.6 * torch.randn(x.shape, generator=g)
    assert float(ssim(x, very).mean()) < float(ssim(x, noisy).mean()) < 1.0
    loss = SSIMGradientLoss()
    assert loss.name == "ssim-grad"
    assert float(loss(x, x)) == pytest.approx(0.0, abs=1e-5)
    assert 0 < float(loss(x, noisy)) < float(loss(x, very))
    # A blurred image keeps its colours but loses its edges, which this loss sees (L1 barely does).
    blurred = F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    assert float(loss(x, blurred)) > 2 * float((x - blurred).abs().mean())
    y = noisy.clone().requires_grad_(True)
    loss(y, x).backward()
    assert y.grad is not None and torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    tiny = torch.zeros(1, 3, 6, 6)
    assert float(loss(tiny, tiny)) == pytest.approx(0.0, abs=1e-6)  # smaller than the SSIM window


def test_missing_lpips_weights_name_the_options(no_hub):
    with pytest.raises(LPIPSWeightsNotFound) as err:
        find_lpips_backbone("vgg")
    msg = str(err.value)
    assert LPIPS_BACKBONE_FILES["vgg"] in msg and "--lpips-weights" in msg
    assert "--perceptual ssim-grad" in msg and "--perceptual none" in msg
    assert str(no_hub / "torch" / "hub" / "checkpoints") in msg  # says where it looked
    # Never a silent switch to another loss.
    with pytest.raises(LPIPSWeightsNotFound):
        build_perceptual("lpips", lpips_net="alex")
    with pytest.raises(LPIPSWeightsNotFound, match="no such file"):
        find_lpips_backbone("alex", no_hub / "nope.pth")
    with pytest.raises(ValueError, match="unknown perceptual"):
        build_perceptual("vgg-style")
    assert build_perceptual("none") is None
    assert isinstance(build_perceptual("ssim-grad"), SSIMGradientLoss)


def _random_alexnet_features(path) -> dict[str, torch.Tensor]:
    """A randomly initialised torchvision AlexNet backbone state dict, saved where the test says."""
    import torchvision  # the train extra installs it with lpips; missing means a broken install

    with torch.device("meta"):  # shapes only; the values are drawn below
        shapes = {k: v.shape for k, v in torchvision.models.alexnet().features.state_dict().items()}
    g = torch.Generator().manual_seed(0)
    state = {f"features.{k}": 0.05 * torch.randn(shape, generator=g) for k, shape in shapes.items()}
    torch.save(state, path)
    return state


def test_lpips_loads_backbone_weights_from_an_explicit_path(no_hub):
    path = no_hub / "my-alexnet.pth"
    state = _random_alexnet_features(path)
    lp = LPIPSLoss("alex", path)
    assert lp.name == "lpips-alex" and lp.weights_path == str(path)
    loaded = lp.model.state_dict()
    # torchvision's features.N.* land in lpips's sliceK.N.*, value for value.
    assert torch.equal(loaded["net.slice1.0.weight"], state["features.0.weight"])
    assert torch.equal(loaded["net.slice5.10.bias"], state["features.10.bias"])
    assert all(not p.requires_grad for p in lp.parameters())
    lp.train()
    assert not lp.model.training  # stays in eval mode (no dropout in the calibrated heads)
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 64, 64, generator=g) * 2 - 1
    y = (x + 0.3 * torch.randn(x.shape, generator=g)).clamp(-1, 1).requires_grad_(True)
    assert torch.allclose(lp.distance(x, x), torch.zeros(2), atol=1e-6)
    d = lp(y, x)
    assert d.item() > 0
    d.backward()
    assert y.grad is not None and torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0


def test_lpips_finds_weights_in_the_torch_hub_cache_and_rejects_the_wrong_net(no_hub):
    hub = no_hub / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    _random_alexnet_features(hub / LPIPS_BACKBONE_FILES["alex"])
    assert find_lpips_backbone("alex") == hub / LPIPS_BACKBONE_FILES["alex"]
    assert isinstance(build_perceptual("lpips", lpips_net="alex"), LPIPSLoss)
    with pytest.raises(ValueError, match="not a torchvision vgg checkpoint"):
        LPIPSLoss("vgg", hub / LPIPS_BACKBONE_FILES["alex"])
    bad = no_hub / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"bad.pth: not a PyTorch file \(torch.save's zip format; LPIPS"):
        LPIPSLoss("alex", bad)
