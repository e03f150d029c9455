"""Network architectures: LP3D encoder, EG3D super-resolution, dual discriminator and GAN losses.

Large configurations are checked on the meta device (shapes and parameter counts, no memory); the
tiny ones run forward and backward on the CPU.
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

torch = pytest.importorskip("torch")
import torch.nn.functional as F  # noqa: E402

from lp3d.nets.discriminator import (  # noqa: E402
    DISCRIMINATOR_CONFIGS,
    DiscriminatorConfig,
    DualDiscriminator,
    build_discriminator,
    d_loss,
    g_loss,
    minibatch_stddev,
    r1_penalty,
)
from lp3d.nets.encoder import (  # noqa: E402
    CONFIGS,
    BasicBlock,
    EncoderConfig,
    build_encoder,
    count_parameters,
    parameter_breakdown,
    pixel_coordinates,
)
from lp3d.nets.stylegan_ops import setup_filter, upfirdn2d, upsample2d  # noqa: E402
from lp3d.nets.superres import SUPERRES_CONFIGS, SuperresConfig, build_superres, modulated_conv2d  # noqa: E402

META = torch.device("meta")


@pytest.fixture(scope="module")
def tiny_encoder():
    torch.manual_seed(0)
    return build_encoder("tiny")


def _image(cfg: EncoderConfig, batch: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 3, cfg.image_size, cfg.image_size, generator=g) * 2 - 1


# --------------------------------------------------------------------------------------------------
# Encoder
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "expected"), [("full", 87e6), ("lt", 63e6)])
def test_paper_configs_parameter_counts_and_shapes_on_meta(name: str, expected: float) -> None:
    cfg = CONFIGS[name]
    with META:
        enc = build_encoder(name)
        out = enc(torch.empty(1, 3, 512, 512))
    total = count_parameters(enc)
    assert abs(total - expected) / expected < 0.10, (
        f"{name}: {total:,} parameters, paper says {expected:,.0f}"
    )
    assert sum(parameter_breakdown(enc).values()) == total
    assert cfg.image_size == 512 and cfg.triplane_resolution == 256
    assert tuple(out.shape) == (1, 3, 32, 256, 256)


def test_lt_differs_from_full_as_the_paper_says() -> None:
    full, lt = CONFIGS["full"], CONFIGS["lt"]
    # "The main difference between the two is in resolution of the intermediate feature maps".
    assert lt.feature_resolution < full.feature_resolution
    # "the input to the LT model's high-resolution encoder is the second layer output features of DeepLabV3".
    assert (full.high_source, lt.high_source) == ("image", "backbone")


@pytest.mark.parametrize("name", ["small", "tiny"])
def test_cpu_configs_sizes(name: str) -> None:
    cfg = CONFIGS[name]
    with META:
        enc = build_encoder(name)
    n = count_parameters(enc)
    basis = cfg.basis_components * 3 * cfg.plane_channels * cfg.basis_resolution**2
    assert sum(parameter_breakdown(enc).values()) == n
    if name == "tiny":
        assert 1e6 <= n <= 3e6
    else:
        # The network proper stays CPU-sized (with the plane generator); the
        # plane basis (64 planes at 32²) is most of the rest.
        assert 5e6 <= n - basis <= 9.5e6 and basis <= 6.5e6
    assert cfg.image_size <= 256 and cfg.triplane_resolution == cfg.image_size // 2
    # float32 ONNX with the mean offset; the shipped file keeps 40 basis planes in float16 (25 MB budget)
    assert 4 * (n + 3 * 32 * cfg.triplane_resolution**2) <= 64e6


def test_small_forward_shape_on_cpu() -> None:
    cfg = CONFIGS["small"]
    enc = build_encoder(cfg).eval()
    with torch.no_grad():
        out = enc(_image(cfg, batch=1))
    assert out.shape == (1, 3, 32, 64, 64)
    assert torch.isfinite(out).all()


def test_tiny_forward_backward_and_a_few_training_steps(tiny_encoder) -> None:
    enc = tiny_encoder
    cfg = enc.config
    x = _image(cfg)
    out = enc(x)
    assert out.shape == (2, 3, 32, 64, 64) and out.dtype == torch.float32
    assert torch.isfinite(out).all() and 0.01 < out.std().item() < 100.0
    out.square().mean().backward()
    blocks = [m for m in enc.backbone.modules() if isinstance(m, BasicBlock)]
    zero_init = {id(p) for m in blocks for p in m.conv1.parameters()}
    # The plane basis's coefficients start at zero (its last layer is zero), so the layers before it and
    # its components get gradients from the second step on, like the residual branches.
    zero_init |= {id(enc.basis.components), *(id(p) for p in enc.basis.coefficients[1].parameters())}
    # So does the plane generator's output: everything before its last layer waits for that layer.
    zero_init |= {id(p) for name, p in enc.generator.named_parameters() if not name.startswith("to_planes")}
    for name, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        # Residual branches start at zero (Fixup-style), so only their first conv has no gradient yet.
        if id(p) not in zero_init:
            assert p.grad.abs().sum() > 0, f"no gradient reaches {name}"
    # It learns: a few Adam steps on a fixed target lower the loss.
    target = torch.randn(2, 3, 32, 64, 64, generator=torch.Generator().manual_seed(1))
    opt = torch.optim.Adam(enc.parameters(), lr=1e-3)
    losses = []
    for _ in range(3):
        opt.zero_grad()
        loss = F.l1_loss(enc(x), target)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0]


def test_triplane_channel_order_is_eg3d(tiny_encoder) -> None:
    captured = {}
    handles = [
        m.register_forward_hook(lambda m, i, o, name=name: captured.setdefault(name, o))
        for name, m in (
            ("head", tiny_encoder.head),
            ("basis", tiny_encoder.basis),
            ("generator", tiny_encoder.generator),
        )
    ]
    try:
        with torch.no_grad():
            out = tiny_encoder(_image(tiny_encoder.config, batch=1))
    finally:
        for h in handles:
            h.remove()
    # (1, 96, T, T): the three branches in the same channel order
    flat = captured["head"] + captured["basis"] + captured["generator"]
    for p in range(3):
        assert torch.equal(out[:, p], flat[:, p * 32 : (p + 1) * 32])


def test_plane_generator_starts_at_zero_and_moves_every_texel() -> None:
    enc = build_encoder("tiny")
    gen = enc.generator
    assert gen is not None
    feats = torch.randn(2, enc.config.aspp_channels, 16, 16, generator=torch.Generator().manual_seed(2))
    out = gen(feats)
    t = enc.config.triplane_resolution
    assert out.shape == (2, 96, t, t) and not out.any()  # an untrained generator adds nothing
    out.square().sum().backward()  # no gradient before its last layer moves; its last layer gets one
    for p in gen.to_planes.parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        gen.to_planes.weight.normal_(0.0, 0.1, generator=g)
        moved = gen(feats)
    # Per texel, not a basis of a few smooth planes: two inputs differ at almost every texel.
    assert float((moved[0] != moved[1]).float().mean()) > 0.99


def test_colour_grid_reaches_the_codes_and_only_through_them() -> None:
    """colour_pool: the input's mean colours, pooled to P², join the basis's and the generator's code
    inputs; a config without it keeps the saved weights' shapes (the shipped model still loads)."""
    plain, coloured = CONFIGS["tiny"], CONFIGS["tiny-colour"]
    assert coloured.code_inputs == plain.code_inputs + 3 * 8**2
    keys = {k: v.shape for k, v in build_encoder(plain).state_dict().items()}
    enc = build_encoder(coloured).eval()
    widened = {k for k, v in enc.state_dict().items() if keys[k] != v.shape}
    assert widened == {"basis.coefficients.1.weight", "generator.code.1.weight"}
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():  # untrained, both branches add zero: give their last layers weights
        enc.basis.coefficients[-1].weight.normal_(0.0, 0.1, generator=g)
        enc.generator.to_planes.weight.normal_(0.0, 0.1, generator=g)
    x = _image(coloured, batch=1)
    from lp3d.nets.plane_basis import code_input

    feats = torch.randn(1, coloured.aspp_channels, 16, 16, generator=g)
    shifted = x.clone()
    shifted[:, 0, 112:] += 0.3  # the bottom 16 rows (a shirt) redder: the grid's bottom row
    a = code_input(feats, coloured.basis_pool, F.adaptive_avg_pool2d(x, 8))
    b = code_input(feats, coloured.basis_pool, F.adaptive_avg_pool2d(shifted, 8))
    changed = (a != b).flatten().nonzero().flatten().tolist()
    first_colour = coloured.aspp_channels * coloured.basis_pool**2
    # The red channel's 64 inputs come first, row by row: its bottom row is inputs 56..63 of the grid.
    assert changed == [first_colour + i for i in range(56, 64)]
    with torch.no_grad():
        for layer in (enc.basis.coefficients[1], enc.generator.code[1]):  # a grid the code listens to
            layer.weight[:, first_colour:].normal_(0.0, 1.0, generator=g)
        base, red = enc(x), enc(shifted)
        for layer in (enc.basis.coefficients[1], enc.generator.code[1]):
            layer.weight[:, first_colour:] = 0.0
        # With the grid's weights zeroed the change reaches the planes through the deep features only.
        blind = enc(shifted) - enc(x)
    assert (red - base - blind).abs().mean() > 0.1 * blind.abs().mean()


def test_colour_pool_is_checked() -> None:
    with pytest.raises(ValueError, match=r"colour_pool \(48\) must divide the image_size"):
        dataclasses.replace(CONFIGS["tiny"], colour_pool=48)
    with pytest.raises(ValueError, match="colour_pool must be an int >= 0"):
        dataclasses.replace(CONFIGS["tiny"], colour_pool=-1)
    with pytest.raises(ValueError, match="colour_pool feeds the basis and the generator"):
        dataclasses.replace(CONFIGS["tiny"], colour_pool=8, basis_components=0, generator_channels=())


@pytest.mark.parametrize("widths", [(64,), (64, 32, 32, 32, 32, 32, 32, 32)])
def test_plane_generator_widths_are_checked(widths) -> None:
    with pytest.raises(ValueError, match="generator_channels"):
        dataclasses.replace(CONFIGS["tiny"], generator_channels=widths)


def test_pixel_coordinates() -> None:
    xy = pixel_coordinates(2, 5, device=torch.device("cpu"), dtype=torch.float32)
    assert xy.shape == (2, 2, 5, 5)
    assert torch.allclose(xy[0, 0, 3], torch.linspace(-1, 1, 5))  # x varies along columns
    assert torch.allclose(xy[0, 1, :, 3], torch.linspace(-1, 1, 5))  # y varies along rows


@pytest.mark.parametrize(
    ("shape", "match"),
    [
        ((2, 3, 64, 64), r"image size must be 128x128 .*got 64x64"),
        ((2, 3, 128, 96), r"image size must be 128x128 .*got 128x96"),
        ((2, 4, 128, 128), r"3 channels .*got 4 channels"),
        ((2, 5, 128, 128), r"appends the 2 coordinate channels itself"),
        ((3, 128, 128), r"shape \(B, 3, 128, 128\), got \(3, 128, 128\)"),
        ((0, 3, 128, 128), r"batch is empty"),
    ],
)
def test_encoder_rejects_bad_shapes(tiny_encoder, shape, match) -> None:
    with pytest.raises(ValueError, match=match):
        tiny_encoder(torch.zeros(shape))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_encoder_rejects_non_finite_values_naming_the_batch_item(tiny_encoder, bad) -> None:
    x = _image(tiny_encoder.config, batch=3)
    x[1, 2, 10, 20] = bad
    with pytest.raises(ValueError, match=r"NaN or Inf values in batch item\(s\) \[1\]"):
        tiny_encoder(x)


def test_encoder_rejects_integer_images(tiny_encoder) -> None:
    with pytest.raises(ValueError, match="floating-point"):
        tiny_encoder(torch.zeros(1, 3, 128, 128, dtype=torch.uint8))


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_encoder_config_json_round_trip(name: str) -> None:
    cfg = CONFIGS[name]
    back = EncoderConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg and hash(back) == hash(cfg)
    assert EncoderConfig.named(name) is cfg


def test_encoder_config_validation() -> None:
    with pytest.raises(ValueError, match="unknown keys"):
        EncoderConfig.from_dict({**CONFIGS["tiny"].to_dict(), "dropout": 0.1})
    with pytest.raises(ValueError, match="feature_resolution"):
        EncoderConfig(feature_resolution=96, triplane_resolution=192)
    with pytest.raises(ValueError, match="triplane_resolution"):
        EncoderConfig(triplane_resolution=200)
    with pytest.raises(ValueError, match="high_source"):
        EncoderConfig(high_source="depth")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="single downsampling stage"):
        EncoderConfig(feature_resolution=128)  # the image would need two stride-2 stages
    with pytest.raises(ValueError, match="low_heads"):
        EncoderConfig(low_heads=3)
    with pytest.raises(ValueError, match="unknown encoder config"):
        build_encoder("huge")


def test_encoder_cli_prints_counts(capsys) -> None:
    from lp3d.nets.encoder import _main

    assert _main(["--config", "lt"]) == 0
    text = capsys.readouterr().out
    assert "encoder config 'lt'" in text and "backbone" in text and "head.vit" in text


def test_transformer_parameter_split(tiny_encoder) -> None:
    vit = list(tiny_encoder.transformer_parameters())
    other = list(tiny_encoder.other_parameters())
    assert len(vit) + len(other) == len(list(tiny_encoder.parameters()))
    assert sum(p.numel() for p in vit) == count_parameters(tiny_encoder.e_low.vit) + count_parameters(
        tiny_encoder.head.vit
    )


# --------------------------------------------------------------------------------------------------
# Super-resolution
# --------------------------------------------------------------------------------------------------


def test_superres_eg3d_structure_on_meta() -> None:
    with META:
        sr = build_superres("eg3d")
        out = sr(torch.empty(2, 32, 128, 128))
    assert tuple(out.shape) == (2, 3, 512, 512)
    shapes = {k: tuple(v.shape) for k, v in sr.state_dict().items()}
    # EG3D parameter names and shapes (docs/eg3d-rendering.md §10).
    assert shapes["block0.conv0.weight"] == (256, 32, 3, 3)
    assert shapes["block0.conv0.affine.weight"] == (32, 512)
    assert shapes["block0.conv1.weight"] == (256, 256, 3, 3)
    assert shapes["block0.torgb.weight"] == (3, 256, 1, 1)
    assert shapes["block1.conv0.weight"] == (128, 256, 3, 3)
    assert shapes["block1.conv1.weight"] == (128, 128, 3, 3)
    assert shapes["block1.torgb.weight"] == (3, 128, 1, 1)
    assert shapes["block0.conv0.noise_const"] == (256, 256)
    assert shapes["block1.conv1.noise_const"] == (512, 512)
    assert shapes["w_const"] == (512,)
    assert "w_const" not in dict(sr.named_parameters())  # the paper's w is a constant


def test_superres_tiny_shape_and_gradients() -> None:
    torch.manual_seed(0)
    sr = build_superres("tiny")
    feat = torch.randn(2, 32, 64, 64, requires_grad=True)
    out = sr(feat)
    assert out.shape == (2, 3, 128, 128) and torch.isfinite(out).all()
    out.square().mean().backward()
    assert feat.grad is not None and feat.grad.abs().sum() > 0
    assert feat.grad[:, 3:].abs().sum() > 0  # all 32 channels feed the convs, not just rgb
    for name, p in sr.named_parameters():
        if name.endswith("noise_strength"):
            continue  # noise_mode="none" (EG3D FFHQ) never reads it
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    # A mismatched input resolution is resized first, as in EG3D.
    assert sr(torch.randn(1, 32, 48, 48)).shape == (1, 3, 128, 128)
    # Learned w variant.
    sr_w = build_superres(
        SuperresConfig(**{**SUPERRES_CONFIGS["tiny"].to_dict(), "block_channels": (64,), "learn_w": True})
    )
    sr_w(torch.randn(1, 32, 64, 64)).sum().backward()
    assert sr_w.w_const.grad is not None


def test_superres_rgb_skip_is_fir_upsampled_input() -> None:
    sr = build_superres("tiny")
    with torch.no_grad():
        for block in sr.blocks:
            block.torgb.weight.zero_()
    feat = torch.randn(1, 32, 64, 64)
    feat[:, :3] = 0.25
    out = sr(feat)
    assert torch.allclose(out, upsample2d(feat[:, :3], setup_filter()))
    assert torch.allclose(out[..., 2:-2, 2:-2], torch.full_like(out[..., 2:-2, 2:-2], 0.25))


def test_modulated_upconv_equals_fir_upsample_then_conv() -> None:
    # EG3D's transposed-conv + FIR path is the linear operator "FIR-upsample, then 3×3 conv".
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 4, 8, 8, generator=g, dtype=torch.float64)
    w = torch.randn(5, 4, 3, 3, generator=g, dtype=torch.float64)
    f = setup_filter().double()
    ours = modulated_conv2d(
        x, w, torch.ones(1, 4, dtype=torch.float64), up=2, padding=1, resample_filter=f, demodulate=False
    )
    upsampled = upfirdn2d(x, f, up=2, padding=(3, 2, 3, 2), gain=4)  # one extra pixel each side for the conv
    assert torch.allclose(ours, F.conv2d(upsampled, w.flip(2, 3)), atol=1e-12)


def test_superres_rejects_bad_input() -> None:
    sr = build_superres("tiny")
    with pytest.raises(ValueError, match=r"\(B, 32, R, R\)"):
        sr(torch.zeros(1, 3, 64, 64))
    with pytest.raises(ValueError, match="square"):
        sr(torch.zeros(1, 32, 64, 32))
    with pytest.raises(ValueError, match="power of two"):
        SuperresConfig(input_resolution=64, output_resolution=192, block_channels=(64, 64))
    with pytest.raises(ValueError, match="block_channels"):
        SuperresConfig(block_channels=(256,))


@pytest.mark.parametrize("name", sorted(SUPERRES_CONFIGS))
def test_superres_config_json_round_trip(name: str) -> None:
    cfg = SUPERRES_CONFIGS[name]
    assert SuperresConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


# --------------------------------------------------------------------------------------------------
# Discriminator and losses
# --------------------------------------------------------------------------------------------------


def test_discriminator_eg3d_structure_on_meta() -> None:
    with META:
        d = build_discriminator("eg3d")
        logits = d(torch.empty(4, 3, 512, 512), torch.empty(4, 3, 128, 128))
    assert tuple(logits.shape) == (4, 1)
    assert d.b512.fromrgb.weight.shape == (64, 6, 1, 1)  # image ⊕ upsampled image_raw
    assert d.block_resolutions == [512, 256, 128, 64, 32, 16, 8]


def test_discriminator_tiny_shapes() -> None:
    torch.manual_seed(0)
    d = build_discriminator("tiny")
    with torch.no_grad():
        logits = d(torch.randn(3, 3, 128, 128), torch.randn(3, 3, 64, 64))  # batch 3: mbstd groups of 3
    assert logits.shape == (3, 1) and torch.isfinite(logits).all()
    with pytest.raises(ValueError, match=r"image must have shape \(B, 3, 128, 128\)"):
        d(torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 32, 32))
    with pytest.raises(ValueError, match="image_raw"):
        d(torch.zeros(2, 3, 128, 128), torch.zeros(1, 3, 64, 64))


def test_r1_penalty_through_the_discriminator() -> None:
    torch.manual_seed(0)
    d = DualDiscriminator(DiscriminatorConfig(name="r1", resolution=32, channel_base=512, channel_max=32))
    img = torch.randn(2, 3, 32, 32, requires_grad=True)
    raw = torch.randn(2, 3, 16, 16, requires_grad=True)
    pen = r1_penalty(d(img, raw), [img, raw])
    assert pen.shape == (2,) and (pen > 0).all()
    (pen.mean() * 0.5).backward()  # differentiable (create_graph=True)
    assert d.b32.fromrgb.weight.grad is not None and d.b32.fromrgb.weight.grad.abs().sum() > 0


def test_discriminator_camera_conditioning() -> None:
    cfg = DiscriminatorConfig(
        name="c", resolution=32, channel_base=512, channel_max=32, c_dim=25, mapping_layers=2
    )
    d = DualDiscriminator(cfg)
    assert d(torch.randn(2, 3, 32, 32), torch.randn(2, 3, 16, 16), torch.randn(2, 25)).shape == (2, 1)
    with pytest.raises(ValueError, match="camera c"):
        d(torch.randn(2, 3, 32, 32), torch.randn(2, 3, 16, 16))
    assert not hasattr(build_discriminator("tiny"), "mapping")  # off by default


def test_r1_penalty_matches_analytic_gradient() -> None:
    a = torch.randn(1, 3, 4, 4)
    img = torch.randn(2, 3, 4, 4, requires_grad=True)
    logits = (img * a).sum(dim=(1, 2, 3)).unsqueeze(1)  # d logit / d img = a
    assert torch.allclose(r1_penalty(logits, [img]), a.square().sum().expand(2))


def test_minibatch_stddev_groups() -> None:
    x = torch.randn(6, 8, 4, 4)
    assert minibatch_stddev(x, 4, 1).shape == (6, 9, 4, 4)  # group of 3 (largest divisor of 6 ≤ 4)
    same = torch.ones(4, 8, 4, 4)
    assert torch.allclose(minibatch_stddev(same, 4, 1)[:, 8], torch.full((4, 4, 4), 1e-4))


def test_gan_loss_signs() -> None:
    zero = torch.zeros(4, 1)
    assert math.isclose(d_loss(zero, zero).item(), 2 * math.log(2), rel_tol=1e-6)
    assert math.isclose(g_loss(zero).item(), math.log(2), rel_tol=1e-6)
    # A discriminator that is right (real high, fake low) has a small loss; the generator's is then large.
    right_real, right_fake = torch.full((4, 1), 5.0), torch.full((4, 1), -5.0)
    assert d_loss(right_real, right_fake) < 0.05 < d_loss(right_fake, right_real)
    assert g_loss(right_fake) > 4.0 > g_loss(right_real)
    real = torch.zeros(4, 1, requires_grad=True)
    fake = torch.zeros(4, 1, requires_grad=True)
    d_loss(real, fake).backward()
    assert (real.grad < 0).all() and (fake.grad > 0).all()  # D pushes real logits up, fake down
    fake_g = torch.zeros(4, 1, requires_grad=True)
    g_loss(fake_g).backward()
    assert (fake_g.grad < 0).all()  # G pushes fake logits up


@pytest.mark.parametrize("name", sorted(DISCRIMINATOR_CONFIGS))
def test_discriminator_config_json_round_trip(name: str) -> None:
    cfg = DISCRIMINATOR_CONFIGS[name]
    assert DiscriminatorConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
