"""EG3D teacher: an adapter that turns a user-supplied EG3D generator into :class:`~lp3d.teachers.Teacher`.

The paper distills from a frozen EG3D FFHQ generator (supplement, "EG3D pre-trained model":
``ffhqrebalanced512-128.pkl``). Its weights cannot ship with lp3d, so :meth:`EG3DTeacher.from_pickle`
loads an official network pickle that the user supplies, and :class:`EG3DTeacher` itself wraps any
object with EG3D's ``TriPlaneGenerator`` interface (the tests use a small stand-in).

What the adapter uses of the generator (``training/triplane.py`` in NVlabs/eg3d)::

    G.z_dim, G.c_dim, G.w_dim
    G.mapping(z (B, z_dim), c (B, c_dim), truncation_psi=, truncation_cutoff=) -> ws (B, num_ws, w_dim)
    G.backbone.synthesis(ws, update_emas=False, noise_mode=) -> planes (B, 96, H, W)  [H = W = 256]
    G.backbone.mapping.w_avg (w_dim,)                          only for sr_w="mean"
    G.decoder.net = [FullyConnectedLayer(32, 64), Softplus(), FullyConnectedLayer(64, 33)]
    G.superresolution(rgb (B, 3, R, R), feature_image (B, 32, R, R), ws, noise_mode=) -> (B, 3, 512, 512)
    G.rendering_kwargs: box_warp, ray_start, ray_end, depth_resolution, depth_resolution_importance, ...
    G.neural_rendering_resolution                               128 for the *-128.pkl checkpoints

Choices (``docs/eg3d-rendering.md`` §4, §5, §10, §11):

* **z**: ``np.random.RandomState(seed).randn(1, z_dim)``, exactly as EG3D's ``gen_samples.py`` and
  ``gen_videos.py`` draw it.
* **Pose conditioning** (mapping only): a camera looking at ``avg_camera_pivot`` from
  ``avg_camera_radius`` (FFHQ: (0, 0, 0.2) and 2.7; read from ``rendering_kwargs`` when present),
  built as one of EG3D's scripts builds it (:func:`default_conditioning_pose`):
  ``conditioning="gen_videos"`` (the default) is ``gen_videos.py``'s
  ``LookAtPoseSampler.sample(3.14/2, 3.14/2, ...)`` with focal 4.2647; as 3.14 is not pi, that camera
  is 0.04563° of yaw toward -x and 0.02905° of pitch above the frontal one. ``"gen_samples"`` is
  ``gen_samples.py``'s exactly frontal ``sample(np.pi/2, np.pi/2, ...)`` with the focal of its
  18.837° field of view, 4.26339 (:data:`CONDITIONING_CAMERAS`). The 0.05° alone moves a full-size
  generator's ws by about 1e-3. ``G.mapping`` itself applies ``c_gen_conditioning_zero`` and
  ``c_scale``. With the same truncation, ``sample(17)`` is the head ``gen_videos.py --seeds 17``
  renders (same ws, same const noise); with ``conditioning="gen_samples"`` its ws are those of
  ``gen_samples.py --seeds 17``, whose noise differs (below).
* **Truncation**: ``truncation_psi = 0.7``, ``truncation_cutoff = 14`` (all 14 ws of the 256² backbone)
  by default, the value of EG3D's README examples. The paper does not state one.
* **Backbone noise**: ``noise_mode = "const"`` (the stored ``noise_const`` buffers) so a seed gives the
  same planes on every call, as ``gen_videos.py`` renders; ``gen_samples.py`` leaves StyleGAN2's
  default ``"random"``, so its images of a seed vary from run to run.
* **Super-resolution w**: the supplement replaces "the latent code W injected to the StyleGAN2-based
  super-resolution layer with a constant 1", i.e. ``w = (1, 1, ..., 1)`` (w_dim ones) for every sample,
  and fine-tunes the whole EG3D model that way for 6.8M images. That is the default (``sr_w="ones"``), as
  in :mod:`lp3d.nets.superres`. Caveat: the *released* EG3D pickles were trained with the sample's own w, so
  their SR module has never seen all-ones and its output is off-distribution; for those, ``sr_w="mean"``
  (the mapping network's tracked average ``w_avg``, i.e. the w of truncation psi = 0) is the closest
  constant. Noise: ``"none"`` (EG3D's FFHQ ``superresolution_noise_mode``).

Loading a pickle executes code: EG3D pickles embed the Python source of their classes and run it when
unpickled. lp3d only loads one through :meth:`EG3DTeacher.from_pickle` (or :func:`load_eg3d_generator`),
on the user's explicit request; load only files you trust.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from lp3d.render.camera import (
    FFHQ_FOCAL,
    FFHQ_PIVOT,
    FFHQ_RADIUS,
    intrinsics,
    lookat_pose,
    pack_label,
    validate_camera,
)
from lp3d.render.settings import RenderSettings
from lp3d.render.triplane import TriplaneData
from lp3d.teachers.eg3d_decoder import (
    eg3d_decoder_weights,
    generator_attr,
)
from lp3d.teachers.eg3d_loading import (
    EG3D_HINT,
    EG3D_SOURCE_PACKAGES,
    EG3DLoadError,
    load_eg3d_generator,
)

__all__ = [
    "CONDITIONING_CAMERAS",
    "CONDITIONING_FOCALS",
    "EG3D_HINT",
    "EG3D_SOURCE_PACKAGES",
    "EG3DLoadError",
    "EG3DTeacher",
    "SrW",
    "default_conditioning_pose",
    "load_eg3d_generator",
]


def _eg3d_fov_to_focal(fov_degrees: float) -> float:
    """The normalised focal length EG3D's ``FOV_to_intrinsics`` gives for a field of view: it uses
    3.14159 for pi and 1.414 for the diagonal factor, so the rounding is kept here on purpose."""
    return 1.0 / (math.tan(fov_degrees * 3.14159 / 360.0) * 1.414)


#: The conditioning camera of EG3D's two generation scripts as ``(h, v, focal)``: the angles its
#: ``LookAtPoseSampler.sample(h, v, pivot, radius=...)`` is given (radians) and the normalised focal
#: length. ``gen_videos.py`` writes ``3.14/2`` for both angles, not pi/2, so its camera is slightly off
#: frontal (yaw -0.04563°, pitch +0.02905° in :func:`lp3d.render.camera.look_at_camera`'s terms); kept on
#: purpose, since the mapping's ws depend on it (about 1e-3). Its focal is written as 4.2647;
#: ``gen_samples.py`` uses ``np.pi/2`` and derives the focal from its default ``--fov-deg 18.837``.
CONDITIONING_CAMERAS: dict[str, tuple[float, float, float]] = {
    "gen_videos": (3.14 / 2, 3.14 / 2, FFHQ_FOCAL),
    "gen_samples": (math.pi / 2, math.pi / 2, _eg3d_fov_to_focal(18.837)),
}
#: The focal length alone of each script's conditioning camera (:data:`CONDITIONING_CAMERAS`).
CONDITIONING_FOCALS: dict[str, float] = {name: cam[2] for name, cam in CONDITIONING_CAMERAS.items()}
Conditioning = Literal["gen_videos", "gen_samples"]

NoiseMode = Literal["const", "none", "random"]
#: The super-resolution w: "ones" (the paper), "mean" (``w_avg``) or an explicit (w_dim,) vector.
SrW = Literal["ones", "mean"] | np.ndarray | Tensor


# --------------------------------------------------------------------------------------------------
# Loading


# --------------------------------------------------------------------------------------------------
# The adapter


def default_conditioning_pose(
    rendering_kwargs: dict[str, Any] | None = None, conditioning: Conditioning = "gen_videos"
) -> np.ndarray:
    """The camera (25,) float64 that the EG3D script ``conditioning`` names conditions the mapping on.

    Looks at ``avg_camera_pivot`` from ``avg_camera_radius`` (from ``rendering_kwargs``; FFHQ defaults
    (0, 0, 0.2) and 2.7), from that script's angles and with its focal length
    (:data:`CONDITIONING_CAMERAS`: ``gen_videos.py``'s is 0.05° off frontal, ``gen_samples.py``'s
    frontal).
    """
    if conditioning not in CONDITIONING_CAMERAS:
        raise ValueError(f"conditioning must be one of {sorted(CONDITIONING_CAMERAS)}, got {conditioning!r}")
    rk = rendering_kwargs or {}
    pivot = tuple(float(v) for v in rk.get("avg_camera_pivot", FFHQ_PIVOT))
    radius = float(rk.get("avg_camera_radius", FFHQ_RADIUS))
    h, v, focal = CONDITIONING_CAMERAS[conditioning]
    return pack_label(lookat_pose(h, v, radius=radius, lookat=pivot), intrinsics(focal))


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**32:
        raise ValueError(f"seed must be an int in [0, 2**32) (numpy RandomState, as EG3D), got {seed!r}")
    return int(seed)


class EG3DTeacher:
    """A frozen EG3D generator as a :class:`~lp3d.teachers.Teacher` (see the module docstring).

    ``generator``: any object with EG3D's ``TriPlaneGenerator`` interface (module docstring). If it is a
    ``torch.nn.Module`` it is moved to ``device``, put in eval mode and frozen, in place.
    ``truncation_psi``/``truncation_cutoff``: passed to ``G.mapping`` (``cutoff=None``: all ws).
    ``conditioning_pose``: (25,) camera label for the mapping; None: :func:`default_conditioning_pose`
    with ``conditioning`` ("gen_videos" or "gen_samples": whose conditioning camera, see the module
    docstring).
    ``noise_mode``: the backbone's StyleGAN2 noise ("const" keeps seeds deterministic).
    ``sr_w``: the super-resolution w, "ones" (the paper's constant 1), "mean" (``w_avg``) or a (w_dim,)
    vector. ``sr_noise_mode``: noise of the super-resolution network ("none", EG3D's FFHQ setting).
    ``max_batch``: seeds per generator call in :meth:`sample_batch`.
    """

    def __init__(
        self,
        generator: Any,
        *,
        device: str | torch.device = "cpu",
        truncation_psi: float = 0.7,
        truncation_cutoff: int | None = 14,
        conditioning_pose: np.ndarray | None = None,
        conditioning: Conditioning = "gen_videos",
        noise_mode: NoiseMode = "const",
        sr_w: SrW = "ones",
        sr_noise_mode: NoiseMode = "none",
        max_batch: int = 8,
    ) -> None:
        self.device = torch.device(device)
        for attr in ("z_dim", "c_dim", "mapping", "backbone.synthesis", "decoder.net", "rendering_kwargs"):
            generator_attr(generator, attr)
        if isinstance(generator, torch.nn.Module):
            generator = generator.to(self.device).eval().requires_grad_(False)
        self.generator = generator
        self.z_dim = int(generator.z_dim)
        self.c_dim = int(generator.c_dim)

        psi = float(truncation_psi)
        if not math.isfinite(psi):
            raise ValueError(f"truncation_psi must be finite, got {truncation_psi!r}")
        if truncation_cutoff is not None and (
            isinstance(truncation_cutoff, bool) or int(truncation_cutoff) < 0
        ):
            raise ValueError(f"truncation_cutoff must be None or an int >= 0, got {truncation_cutoff!r}")
        self.truncation_psi = psi
        self.truncation_cutoff = None if truncation_cutoff is None else int(truncation_cutoff)
        for name, mode in (("noise_mode", noise_mode), ("sr_noise_mode", sr_noise_mode)):
            if mode not in ("const", "none", "random"):
                raise ValueError(f"{name} must be 'const', 'none' or 'random', got {mode!r}")
        self.noise_mode: NoiseMode = noise_mode
        self.sr_noise_mode: NoiseMode = sr_noise_mode
        if isinstance(max_batch, bool) or int(max_batch) < 1:
            raise ValueError(f"max_batch must be an int >= 1, got {max_batch!r}")
        self.max_batch = int(max_batch)

        rk = generator.rendering_kwargs
        if not isinstance(rk, dict):
            raise TypeError(f"generator.rendering_kwargs must be a dict, got {type(rk).__name__}")
        self.rendering_kwargs: dict[str, Any] = rk
        self._bounds = self._scene_bounds(rk)

        if conditioning_pose is None:
            conditioning_pose = default_conditioning_pose(rk, conditioning)
        cams, batched = validate_camera(conditioning_pose)
        if batched:
            raise ValueError(
                f"conditioning_pose must be one (25,) label, got shape {np.shape(conditioning_pose)}"
            )
        self.conditioning_pose: np.ndarray = cams[0]
        if self.c_dim not in (0, cams.shape[1]):
            raise ValueError(f"generator.c_dim must be 0 or 25 (an EG3D camera label), got {self.c_dim}")

        self._decoder = eg3d_decoder_weights(generator.decoder)
        self._sr_w_spec = sr_w
        self._sr_w_vec: Tensor | None = None
        self.sr_w()  # resolve now so a bad sr_w fails at construction

    @classmethod
    def from_pickle(
        cls,
        path: str | os.PathLike[str] | None,
        *,
        eg3d_source: str | os.PathLike[str] | None = None,
        device: str | torch.device = "cpu",
        truncation_psi: float = 0.7,
        truncation_cutoff: int | None = 14,
        conditioning_pose: np.ndarray | None = None,
        conditioning: Conditioning = "gen_videos",
        noise_mode: NoiseMode = "const",
        sr_w: SrW = "ones",
        sr_noise_mode: NoiseMode = "none",
        max_batch: int = 8,
    ) -> EG3DTeacher:
        """Load an official EG3D generator pickle (its ``G_ema``) and wrap it.

        **Unpickling executes code from the file**: call this only when the user asked for it, on a
        pickle they trust. ``eg3d_source``: a checkout of NVlabs/eg3d's ``eg3d/`` folder, on
        ``sys.path`` for unpickling only. Errors: :class:`EG3DLoadError` (see :func:`load_eg3d_generator`).
        The other arguments are those of :class:`EG3DTeacher`; a pickle whose ``G_ema`` lacks EG3D's
        interface (a StyleGAN2 generator, say) is an :class:`EG3DLoadError` naming what is missing.
        """
        generator = load_eg3d_generator(path, eg3d_source=eg3d_source)
        try:
            return cls(
                generator,
                device=device,
                truncation_psi=truncation_psi,
                truncation_cutoff=truncation_cutoff,
                conditioning_pose=conditioning_pose,
                conditioning=conditioning,
                noise_mode=noise_mode,
                sr_w=sr_w,
                sr_noise_mode=sr_noise_mode,
                max_batch=max_batch,
            )
        except (TypeError, AttributeError) as e:  # a missing part of the interface (ValueErrors name theirs)
            raise EG3DLoadError(
                f"{str(path)!r} holds a generator lp3d cannot use as an EG3D teacher: {e}. lp3d needs EG3D's "
                "TriPlaneGenerator (e.g. ffhqrebalanced512-128.pkl), not a 2D StyleGAN generator"
            ) from e

    # -- scene ---------------------------------------------------------------------------------------

    @staticmethod
    def _scene_bounds(rk: dict[str, Any]) -> tuple[float, float, float]:
        """``(box_warp, ray_start, ray_end)`` from rendering_kwargs, refusing what lp3d cannot render."""
        missing = [k for k in ("box_warp", "ray_start", "ray_end") if k not in rk]
        if missing:
            raise ValueError(f"generator.rendering_kwargs lacks {missing}")
        if rk["ray_start"] == "auto" or rk["ray_end"] == "auto":
            raise ValueError(
                "rendering_kwargs ray_start/ray_end 'auto' (per-ray box bounds) is not supported"
            )
        if rk.get("clamp_mode", "softplus") != "softplus":
            raise ValueError(f"rendering_kwargs clamp_mode must be 'softplus', got {rk['clamp_mode']!r}")
        if rk.get("disparity_space_sampling", False):
            raise ValueError(
                "rendering_kwargs disparity_space_sampling=True is not supported by lp3d's renderer"
            )
        return float(rk["box_warp"]), float(rk["ray_start"]), float(rk["ray_end"])

    def render_settings(self, *, resolution: int | None = None) -> RenderSettings:
        """The generator's render settings: its neural rendering resolution (128 for *-128.pkl) and S/N."""
        rk = self.rendering_kwargs
        res = (
            resolution
            if resolution is not None
            else getattr(self.generator, "neural_rendering_resolution", 128)
        )
        settings = RenderSettings(
            resolution=int(res),
            depth_resolution=int(rk.get("depth_resolution", 48)),
            depth_resolution_importance=int(rk.get("depth_resolution_importance", 48)),
            white_back=bool(rk.get("white_back", False)),
        )
        settings.validate()
        return settings

    # -- Teacher protocol ----------------------------------------------------------------------------

    def decoder(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Effective decoder weights ``(w0 (64, 32), b0 (64,), w1 (33, 64), b1 (33,))`` float32 (copies).

        ``W_eff = W * lr_multiplier / sqrt(in_features)``, ``b_eff = b * lr_multiplier``
        (``docs/eg3d-rendering.md`` §4): ``h = softplus(w0 f + b0)``, ``o = w1 h + b1`` is the decoder's
        forward.
        """
        w0, b0, w1, b1 = self._decoder
        return w0.copy(), b0.copy(), w1.copy(), b1.copy()

    def latents(self, seeds: Sequence[int]) -> Tensor:
        """Truncated, pose-conditioned ws (B, num_ws, w_dim) float32 on ``device`` for ``seeds``."""
        seeds = [_check_seed(s) for s in seeds]
        if not seeds:
            raise ValueError("latents needs at least one seed")
        # z drawn as EG3D's gen_samples.py and gen_videos.py do, on the CPU, so seeds mean the same
        # on every device.
        z_np = np.concatenate([np.random.RandomState(s).randn(1, self.z_dim) for s in seeds])
        z = torch.from_numpy(z_np).to(self.device, torch.float32)
        c = torch.from_numpy(self.conditioning_pose[: self.c_dim]).to(self.device, torch.float32)
        c = c.unsqueeze(0).repeat(len(seeds), 1)
        with torch.no_grad():
            ws = self.generator.mapping(
                z, c, truncation_psi=self.truncation_psi, truncation_cutoff=self.truncation_cutoff
            )
        return ws

    def planes(self, seeds: Sequence[int]) -> Tensor:
        """Triplanes (B, 3, 32, H, W) float32 on ``device`` (EG3D: H = W = 256) for ``seeds``."""
        ws = self.latents(seeds)
        with torch.no_grad():
            planes = self.generator.backbone.synthesis(ws, update_emas=False, noise_mode=self.noise_mode)
        if planes.ndim != 4 or planes.shape[1] != 96:
            raise ValueError(f"backbone.synthesis must return (B, 96, H, W), got {tuple(planes.shape)}")
        # Same reshape as TriPlaneGenerator.synthesis: channel 32 * p + k is channel k of plane p.
        return planes.float().reshape(len(planes), 3, 32, planes.shape[-2], planes.shape[-1])

    def sample(self, seed: int) -> TriplaneData:
        """One identity: planes (3, 32, 256, 256) float32, the effective decoder and the scene bounds."""
        return self.sample_batch([seed])[0]

    def sample_batch(self, seeds: Sequence[int]) -> list[TriplaneData]:
        """``[sample(s) for s in seeds]``, ``max_batch`` seeds per generator call.

        Each seed's z is drawn alone, so batching changes no input; outputs can differ from
        :meth:`sample`'s in the last float32 bits where batched kernels round differently.
        """
        out: list[TriplaneData] = []
        seeds = list(seeds)
        box_warp, ray_start, ray_end = self._bounds
        for i in range(0, len(seeds), self.max_batch):
            chunk = seeds[i : i + self.max_batch]
            planes = self.planes(chunk).cpu().numpy()
            for seed, p in zip(chunk, planes, strict=True):
                w0, b0, w1, b1 = self.decoder()
                out.append(
                    TriplaneData(
                        planes=np.ascontiguousarray(p, dtype=np.float32),
                        w0=w0,
                        b0=b0,
                        w1=w1,
                        b1=b1,
                        box_warp=box_warp,
                        ray_start=ray_start,
                        ray_end=ray_end,
                        source=f"eg3d seed {int(seed)}",
                    )
                )
        return out

    # -- super-resolution ----------------------------------------------------------------------------

    def sr_w(self) -> Tensor:
        """The constant super-resolution w (w_dim,) float32 on ``device`` (see ``sr_w`` in the class doc)."""
        if self._sr_w_vec is None:
            spec = self._sr_w_spec
            w_avg = getattr(
                getattr(getattr(self.generator, "backbone", None), "mapping", None), "w_avg", None
            )
            w_dim = getattr(self.generator, "w_dim", None)
            if w_dim is None and w_avg is not None:
                w_dim = int(w_avg.shape[-1])
            if isinstance(spec, str) and spec == "ones":
                if w_dim is None:
                    raise TypeError("sr_w='ones' needs generator.w_dim")
                vec = torch.ones(int(w_dim))  # the paper's "constant 1"
            elif isinstance(spec, str) and spec == "mean":
                if w_avg is None:
                    raise TypeError("sr_w='mean' needs generator.backbone.mapping.w_avg")
                vec = torch.as_tensor(w_avg).detach().clone()
            elif isinstance(spec, str):
                raise ValueError(f"sr_w must be 'ones', 'mean' or a (w_dim,) vector, got {spec!r}")
            else:
                vec = torch.as_tensor(spec).detach().clone()
                if vec.ndim != 1 or (w_dim is not None and vec.shape[0] != int(w_dim)):
                    raise ValueError(f"sr_w must have shape ({w_dim},), got {tuple(vec.shape)}")
            self._sr_w_vec = vec.to(self.device, torch.float32)
        return self._sr_w_vec

    def superresolve(self, feature_image: Tensor | np.ndarray) -> Tensor:
        """EG3D's super-resolution of a rendered feature image with the constant w.

        ``feature_image`` (B, 32, 128, 128) (rgb = its first 3 channels, as ``TriPlaneGenerator``)
        -> image (B, 3, 512, 512) float32 on ``device``, about [-1, 1]. The w fed to
        ``G.superresolution`` is :meth:`sr_w` repeated to (B, num_ws, w_dim) (EG3D's module reads
        only ``ws[:, -1]``); noise mode ``sr_noise_mode``. No gradients: the teacher is frozen.
        """
        sr = generator_attr(self.generator, "superresolution")
        x = torch.as_tensor(feature_image).to(self.device, torch.float32)
        if x.ndim != 4 or x.shape[1] != 32:
            raise ValueError(f"feature_image must have shape (B, 32, R, R), got {tuple(x.shape)}")
        num_ws = int(getattr(self.generator.backbone, "num_ws", 1) or 1)
        w = self.sr_w()
        ws = w.reshape(1, 1, -1).repeat(x.shape[0], num_ws, 1)
        with torch.no_grad():
            img = sr(x[:, :3], x, ws, noise_mode=self.sr_noise_mode)
        return img.float()
