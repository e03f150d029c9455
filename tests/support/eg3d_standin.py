"""A tiny stand-in for EG3D's ``TriPlaneGenerator`` with the attributes that
:class:`lp3d.teachers.eg3d.EG3DTeacher` uses (NVlabs/eg3d ``training/triplane.py``,
``training/networks_stylegan2.py``), for tests.

An importable module (not the test file) so the loader test can pickle a generator and load it back.
Every call records its arguments in ``calls`` so tests can check what the adapter passed.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

PLANE_RES = 16
Z_DIM, C_DIM, W_DIM, NUM_WS = 8, 25, 16, 4


def _randn(g: torch.Generator, *shape: int) -> Tensor:
    return torch.randn(*shape, generator=g)


class FC(nn.Module):
    """StyleGAN2's ``FullyConnectedLayer``: stored ``weight`` (out, in), ``bias``, ``weight_gain``,
    ``bias_gain``.

    ``keep_lr_attr=False`` drops the ``lr_multiplier`` attribute, as in EG3D's real layer.
    """

    def __init__(
        self,
        g: torch.Generator,
        in_features: int,
        out_features: int,
        *,
        lr_multiplier: float = 1.0,
        activation: str = "linear",
        keep_lr_attr: bool = True,
    ) -> None:
        super().__init__()
        self.in_features = in_features
        self.out_features = out_features
        self.activation = activation
        self.weight = nn.Parameter(_randn(g, out_features, in_features) / lr_multiplier)
        # Random (not zero) biases so a forgotten bias gain would show.
        self.bias = nn.Parameter(0.5 * _randn(g, out_features))
        self.weight_gain = lr_multiplier / np.sqrt(in_features)
        self.bias_gain = lr_multiplier
        if keep_lr_attr:
            self.lr_multiplier = lr_multiplier

    def forward(self, x: Tensor) -> Tensor:
        # Verbatim EG3D (networks_stylegan2.FullyConnectedLayer.forward), lrelu via torch.
        w = self.weight.to(x.dtype) * self.weight_gain
        b = self.bias.to(x.dtype)
        if self.bias_gain != 1:
            b = b * self.bias_gain
        if self.activation == "linear":
            return torch.addmm(b.unsqueeze(0), x, w.t())
        return F.leaky_relu(x.matmul(w.t()) + b, 0.2) * np.sqrt(2)


class Mapping(nn.Module):
    """EG3D's ``MappingNetwork`` (2 layers): normalised z, embedded c -> ws (B, NUM_WS, W_DIM), truncated."""

    def __init__(self, g: torch.Generator, c_dim: int = C_DIM) -> None:
        super().__init__()
        self.z_dim, self.c_dim, self.w_dim, self.num_ws = Z_DIM, c_dim, W_DIM, NUM_WS
        if c_dim:
            self.embed = FC(g, c_dim, W_DIM)
        self.fc0 = FC(g, Z_DIM + (W_DIM if c_dim else 0), W_DIM, lr_multiplier=0.01, activation="lrelu")
        self.fc1 = FC(g, W_DIM, W_DIM, lr_multiplier=0.01, activation="lrelu")
        self.register_buffer("w_avg", _randn(g, W_DIM))
        self.calls: list[dict[str, Any]] = []

    def forward(
        self, z: Tensor, c: Tensor, truncation_psi: float = 1, truncation_cutoff: int | None = None
    ) -> Tensor:
        self.calls.append(dict(z=z.clone(), c=c.clone(), psi=truncation_psi, cutoff=truncation_cutoff))

        def norm(v: Tensor) -> Tensor:
            return v * (v.square().mean(dim=1, keepdim=True) + 1e-8).rsqrt()

        x = norm(z.float())
        if self.c_dim:
            x = torch.cat([x, norm(self.embed(c.float()))], dim=1)
        x = self.fc1(self.fc0(x)).unsqueeze(1).repeat(1, self.num_ws, 1)
        if truncation_psi != 1:
            cut = self.num_ws if truncation_cutoff is None else truncation_cutoff
            x[:, :cut] = self.w_avg.lerp(x[:, :cut], truncation_psi)
        return x


class Synthesis(nn.Module):
    """Fake ``SynthesisNetwork``: ws (B, NUM_WS, W_DIM) -> planes (B, 96, PLANE_RES, PLANE_RES) + noise."""

    def __init__(self, g: torch.Generator) -> None:
        super().__init__()
        self.mix = nn.Parameter(_randn(g, 96, NUM_WS * W_DIM) / (NUM_WS * W_DIM) ** 0.5)
        self.register_buffer("basis", _randn(g, 96, PLANE_RES, PLANE_RES))
        self.register_buffer("noise_const", _randn(g, PLANE_RES, PLANE_RES))
        self.noise_strength = nn.Parameter(torch.tensor(0.1))
        self.calls: list[dict[str, Any]] = []

    def forward(self, ws: Tensor, update_emas: bool = False, noise_mode: str = "random") -> Tensor:
        assert noise_mode in ("random", "const", "none")
        self.calls.append(dict(ws=ws.clone(), update_emas=update_emas, noise_mode=noise_mode))
        amp = torch.tanh(ws.flatten(1) @ self.mix.t())  # (B, 96)
        out = amp[:, :, None, None] * self.basis
        if noise_mode == "random":
            out = out + torch.randn(out.shape[0], 1, PLANE_RES, PLANE_RES) * self.noise_strength
        elif noise_mode == "const":
            out = out + self.noise_const * self.noise_strength
        return out


class Backbone(nn.Module):
    def __init__(self, g: torch.Generator, c_dim: int = C_DIM) -> None:
        super().__init__()
        self.num_ws = NUM_WS
        self.mapping = Mapping(g, c_dim)
        self.synthesis = Synthesis(g)


class OSGDecoder(nn.Module):
    """EG3D's decoder: ``net = [FC(32 -> 64), Softplus, FC(64 -> 33)]``."""

    def __init__(self, g: torch.Generator, lr_multiplier: float = 1.0, keep_lr_attr: bool = True) -> None:
        super().__init__()
        kw = dict(lr_multiplier=lr_multiplier, keep_lr_attr=keep_lr_attr)
        self.net = nn.Sequential(FC(g, 32, 64, **kw), nn.Softplus(), FC(g, 64, 33, **kw))


class SuperRes(nn.Module):
    """Fake ``SuperresolutionHybrid8XDC``: (rgb, x, ws) -> (B, 3, 4R, 4R); reads ``ws[:, -1]`` only."""

    def __init__(self, g: torch.Generator) -> None:
        super().__init__()
        self.affine = FC(g, W_DIM, 3)
        self.calls: list[dict[str, Any]] = []

    def forward(self, rgb: Tensor, x: Tensor, ws: Tensor, noise_mode: str = "random") -> Tensor:
        self.calls.append(dict(rgb=rgb.clone(), x=x.clone(), ws=ws.clone(), noise_mode=noise_mode))
        style = self.affine(ws[:, -1])  # (B, 3)
        up = F.interpolate(rgb + x[:, 3:6], scale_factor=4, mode="nearest")
        return up * (1 + 0.1 * style[:, :, None, None])


FFHQ_RENDERING_KWARGS: dict[str, Any] = dict(
    depth_resolution=48,
    depth_resolution_importance=48,
    ray_start=2.25,
    ray_end=3.3,
    box_warp=1,
    avg_camera_radius=2.7,
    avg_camera_pivot=[0, 0, 0.2],
    image_resolution=512,
    disparity_space_sampling=False,
    clamp_mode="softplus",
    superresolution_module="training.superresolution.SuperresolutionHybrid8XDC",
    c_gen_conditioning_zero=False,
    c_scale=1.0,
    superresolution_noise_mode="none",
    density_reg=0.25,
    density_reg_p_dist=0.004,
    reg_type="l1",
    decoder_lr_mul=1.0,
    sr_antialias=True,
)


class StandInGenerator(nn.Module):
    """Same interface as EG3D's ``TriPlaneGenerator`` as far as the adapter uses it; tiny sizes."""

    def __init__(
        self,
        seed: int = 0,
        *,
        c_dim: int = C_DIM,
        decoder_lr_mul: float = 1.0,
        keep_lr_attr: bool = True,
        rendering_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.z_dim, self.c_dim, self.w_dim, self.img_resolution = Z_DIM, c_dim, W_DIM, 512
        self.backbone = Backbone(g, c_dim)
        self.decoder = OSGDecoder(g, decoder_lr_mul, keep_lr_attr)
        self.superresolution = SuperRes(g)
        self.neural_rendering_resolution = 128
        self.rendering_kwargs = dict(FFHQ_RENDERING_KWARGS, decoder_lr_mul=decoder_lr_mul)
        self.rendering_kwargs.update(rendering_kwargs or {})

    def mapping(
        self, z: Tensor, c: Tensor, truncation_psi: float = 1, truncation_cutoff: int | None = None
    ) -> Tensor:
        # As TriPlaneGenerator.mapping: the pose conditioning options live in rendering_kwargs.
        if self.rendering_kwargs["c_gen_conditioning_zero"]:
            c = torch.zeros_like(c)
        return self.backbone.mapping(
            z,
            c * self.rendering_kwargs.get("c_scale", 0),
            truncation_psi=truncation_psi,
            truncation_cutoff=truncation_cutoff,
        )
