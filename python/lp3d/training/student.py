"""The student: :class:`Student` (encoder, decoder and SR), the renders of it and its teacher
(:func:`render_views`, :func:`render_teacher`) and the start of its plane basis
(:func:`principal_planes`). The scene bounds it shares with its teacher are a
:class:`lp3d.render.settings.SceneBounds` (re-exported here as ``SceneBounds``).

Imports :mod:`lp3d.training.config` only."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.nets.encoder import LP3DEncoder
from lp3d.nets.superres import SuperResolution
from lp3d.render.settings import SceneBounds
from lp3d.render.torch_twin import render_torch
from lp3d.render.triplane import TriplaneData, mirror_planes
from lp3d.teachers import Teacher
from lp3d.training import distributed
from lp3d.training.config import TrainConfig
from lp3d.training.losses import ViewRenders


@torch.no_grad()
def principal_planes(
    planes: np.ndarray, k: int, resolution: int, scale: Tensor, *, mirror: bool = False, limit: int = 2048
) -> tuple[Tensor, Tensor]:
    """The mean (3, C, T, T) of teacher triplanes (N, 3, C, T, T) and their first ``k`` principal
    components at ``resolution``², as (k, 3·C, r, r) scaled so unit coefficients are one standard
    deviation (the plane basis's start, :class:`lp3d.nets.encoder.PlaneBasis`).

    Channels are divided by ``scale`` (C,) before the analysis, as in the normalised L_tri, so the
    components favour what that loss weighs. ``mirror`` adds the mirrored planes (the training
    augmentation). At most ``limit`` planes are used (the Gram matrix is limit²)."""
    x = torch.from_numpy(np.asarray(planes[: limit // 2 if mirror else limit], dtype=np.float32))
    if mirror:
        x = torch.cat([x, mirror_planes(x)])
    n, p, c, t, _ = x.shape
    mean = x.mean(0)
    if k == 0:
        return mean, torch.zeros(0, p * c, resolution, resolution)
    if n < 2:
        raise ValueError(f"principal planes need at least 2 planes, got {n}")
    found = min(k, n - 1)  # a small dataset (tests, trials) has n - 1 directions; the rest start at zero
    if found < k:
        distributed.note(f"note: {n} planes give {found} principal planes; {k - found} start at zero")
    small = x.reshape(n, p * c, t, t)
    if resolution != t:
        small = F.interpolate(small, size=(resolution, resolution), mode="bilinear", antialias=True)
    per_channel = scale.repeat(p).reshape(1, p * c, 1, 1)
    z = ((small - small.mean(0, keepdim=True)) / per_channel).reshape(n, -1).double()
    eigval, eigvec = torch.linalg.eigh(z @ z.T)  # ascending; Gram trick: n << dimensions
    eigval, eigvec = eigval.flip(0)[:found].clamp_min(1e-12), eigvec.flip(1)[:, :found]
    # Unit-norm directions u = zᵀv/√λ; one standard deviation along them is √(λ/n).
    directions = (eigvec.T @ z) / eigval.sqrt()[:, None]
    components = directions * (eigval / n).sqrt()[:, None]
    components = components.float().reshape(found, p * c, resolution, resolution) * per_channel
    return mean, torch.cat([components, components.new_zeros(k - found, *components.shape[1:])])


def render_views(
    planes: Tensor,
    decoder: Sequence[Tensor],
    cameras: Tensor,
    config: TrainConfig,
    scene: SceneBounds,
    *,
    resolution: int | None = None,
) -> dict[str, Tensor]:
    """:func:`~lp3d.render.torch_twin.render_torch` of planes (B, 3, 32, T, T) from cameras (B, 25) with a
    training configuration's sample counts (at ``raw_resolution`` unless ``resolution`` is given)."""
    return render_torch(planes, *decoder, cameras, config.render_settings(resolution), bounds=scene)


class TriplaneDecoder(nn.Module):
    """EG3D's OSGDecoder as effective weights w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,)."""

    def __init__(self, w0: np.ndarray, b0: np.ndarray, w1: np.ndarray, b1: np.ndarray) -> None:
        super().__init__()
        self.w0 = nn.Parameter(torch.as_tensor(np.asarray(w0, np.float32)).clone())
        self.b0 = nn.Parameter(torch.as_tensor(np.asarray(b0, np.float32)).clone())
        self.w1 = nn.Parameter(torch.as_tensor(np.asarray(w1, np.float32)).clone())
        self.b1 = nn.Parameter(torch.as_tensor(np.asarray(b1, np.float32)).clone())

    def weights(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.w0, self.b0, self.w1, self.b1


class Student(nn.Module):
    """E, its decoder and its SR. ``encode(image (B,3,S,S)) -> planes (B,3,32,T,T)``;
    ``render(planes, cameras (B,25)) -> ViewRenders`` (features (B,32,r,r), high (B,3,S,S),
    depth (B,r,r)).

    With ``config.mean_triplane_offset`` the triplane is ``E(I) + plane_offset``, a learned
    (3, 32, T, T) offset (see :class:`TrainConfig`); otherwise ``plane_offset`` is None.
    """

    def __init__(
        self,
        config: TrainConfig,
        decoder: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        scene: SceneBounds,
    ) -> None:
        super().__init__()
        self.config = config
        self.scene = scene
        self.encoder = LP3DEncoder(config.encoder)
        self.decoder = TriplaneDecoder(*decoder)
        self.superres = SuperResolution(config.superres)
        if config.mean_triplane_offset:
            t, c = config.triplane_resolution, config.encoder.plane_channels
            self.plane_offset = nn.Parameter(torch.zeros(3, c, t, t))
        else:
            self.register_parameter("plane_offset", None)

    def encode(self, image: Tensor, *, amp: bool = False) -> Tensor:
        with torch.autocast(image.device.type, dtype=torch.float16, enabled=amp):
            planes = self.encoder(image)
        planes = planes.float()
        return planes if self.plane_offset is None else planes + self.plane_offset

    @torch.no_grad()
    def start_from_mean(self, mean_planes: Tensor) -> None:
        """Set ``plane_offset`` to a mean teacher triplane (3, 32, T, T) and zero the encoder's last
        convolution, so that the untrained student outputs exactly the mean triplane."""
        if self.plane_offset is None:
            raise ValueError("start_from_mean needs config.mean_triplane_offset")
        self.plane_offset.copy_(mean_planes.to(self.plane_offset))
        last = self.encoder.head.out_convs[-1]
        assert isinstance(last, nn.Conv2d)
        last.weight.zero_()
        if last.bias is not None:
            last.bias.zero_()

    def render(
        self,
        planes: Tensor,
        cameras: Tensor,
        *,
        resolution: int | None = None,
        freeze_superres: bool = False,
    ) -> ViewRenders:
        """Render planes (B, 3, 32, T, T) from cameras (B, 25). ``freeze_superres``: gradients reach
        the planes through the SR but not the SR's parameters (stage 1, where the paper's SR is frozen)."""
        out = render_views(
            planes, self.decoder.weights(), cameras, self.config, self.scene, resolution=resolution
        )
        features = out["features"]
        if self.config.recipe == "cpu":
            # No SR in the CPU recipe: the final image is a volume render at the image size, as the
            # procedural teacher's is (and as ``lp3d render`` draws an encoded triplane).
            high = render_views(
                planes,
                self.decoder.weights(),
                cameras,
                self.config,
                self.scene,
                resolution=self.config.image_size,
            )["rgb"]
            return ViewRenders(features=features, high=high, depth=out["depth"])
        if freeze_superres:
            frozen = {k: v.detach() for k, v in self.superres.named_parameters()}
            high = torch.func.functional_call(self.superres, frozen, (features,))
        else:
            high = self.superres(features)
        return ViewRenders(features=features, high=high, depth=out["depth"])

    def triplane(
        self, planes: Tensor, *, camera: np.ndarray | None = None, source: str | None = None
    ) -> TriplaneData:
        """One encoded triplane (3, 32, T, T) as a self-contained :class:`TriplaneData`."""
        w = [t.detach().cpu().numpy() for t in self.decoder.weights()]
        return TriplaneData(
            planes=planes.detach().float().cpu().numpy(),
            w0=w[0],
            b0=w[1],
            w1=w[2],
            b1=w[3],
            box_warp=self.scene.box_warp,
            ray_start=self.scene.ray_start,
            ray_end=self.scene.ray_end,
            camera=camera,
            source=source,
        )


def render_teacher(
    teacher: Teacher,
    planes: Tensor,
    decoder: Sequence[Tensor],
    cameras: Tensor,
    config: TrainConfig,
    scene: SceneBounds,
    *,
    raw: bool = True,
    high: bool = True,
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """The teacher's ``(features (B,32,r,r), depth (B,r,r), high (B,3,S,S))`` for cameras (B, 25).

    ``high`` is the teacher's super-resolution of its raw render when it has one (``superresolve``,
    EG3D; resized to S with antialiasing when its output differs, e.g. 512 -> 128 for a CPU
    configuration), else a direct volume render at the image size (procedural). Parts not asked for
    are None.
    """
    sr = getattr(teacher, "superresolve", None)
    features = depth = image = None
    with torch.no_grad():
        if raw or (high and sr is not None):
            out = render_views(planes, decoder, cameras, config, scene)
            features, depth = out["features"], out["depth"]
        if high:
            if sr is not None:
                image = sr(features).to(planes.device, torch.float32)
                s = config.image_size
                if image.ndim == 4 and tuple(image.shape[-2:]) != (s, s):
                    image = F.interpolate(image, size=(s, s), mode="bilinear", antialias=True)
            else:
                image = render_views(planes, decoder, cameras, config, scene, resolution=config.image_size)
                image = image["rgb"]
    return features, depth, image
