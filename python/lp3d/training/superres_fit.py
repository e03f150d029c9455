"""Fit a super-resolution network (SR) for a trained encoder whose recipe has none.

The paper's recipe trains an SR with the encoder (EG3D's, paper Eq. 2); the CPU recipe
(``python -m lp3d.train --config small``, the shipped model) renders its final image directly and
trains none. This module gives such a model one, with the encoder and decoder frozen::

    python -m lp3d.training.superres_fit [MODEL] --out runs/sr-small
    lp3d export --superres runs/sr-small/superres-fit.pt --package MODEL.onnx [--weights MODEL.pt]

``MODEL`` is anything ``lp3d encode --model`` takes (default: the shipped model).

1. **Pairs, made once.** For each of ``identities`` procedural-teacher identities (seeds from
   ``first_seed``, inside the training range but past any CPU dataset, and disjoint from
   ``lp3d.training.eval``'s held-out seeds): the teacher renders the encoder's input from a reference camera
   (:data:`~lp3d.training.camera_sampling.FFHQ_REFERENCE`), the model encodes it, and for ``views`` multiview
   cameras (:data:`~lp3d.training.camera_sampling.FFHQ_MULTIVIEW`) ``lp3d_render`` draws the *student's* raw
   feature image at ``raw_resolution``, the *teacher's* image at ``output_resolution``, and the
   teacher's own raw feature image at ``raw_resolution`` from its head at the student's plane
   resolution (the well-posed pairs EG3D's SR learns from: the same head, low and high). The pairs
   (and ``heldout_identities`` more, from ``heldout_first_seed``) are cached on disk in a folder named
   by a hash of everything they depend on (:class:`PairKey`: the model's weights, the teacher's
   fingerprint, seeds, sizes, samples, cameras); ``meta.json`` records each array's SHA-256, and a
   folder that does not match (edited, truncated, another key) is reported and rebuilt, never used.
2. **Training.** Only the 2-D SR learns (EG3D's architecture with the paper's constant w,
   :class:`lp3d.nets.superres.SuperResolution`): random crops of ``crop``² raw pixels and their teacher
   crops, horizontal flips, L1 + ``ssim-grad`` (the CPU configurations' perceptual loss), Adam with a
   cosine decay. ``train_on`` picks the inputs: ``student`` (its raw renders, mapped to the teacher's
   image: the SR also learns to correct the student, which it mostly cannot), ``teacher`` (the
   teacher's own low-resolution renders: pure super-resolution of the decoder's feature images), or
   ``both`` (the default: half of each batch each). Each ToRGB layer starts at zero, so the network
   starts as FIR upsampling of the raw rgb (about the bilinear baseline) and learns a residual; the
   learning rate is high (1e-2) for a short fit. A checkpoint is written atomically every
   ``checkpoint_every`` steps and at the end; rerunning the same command resumes it.
3. **Held-out score.** PSNR and SSIM of the SR image of the student's raw render against the
   teacher's image on the held-out pairs, beside the same for the student's raw render upsampled
   bilinearly (what the SR must beat to be worth shipping), and the same two for the teacher's own
   low-resolution renders (``teacher_*``); ``report.json`` and ``heldout.png`` (student: upsampled
   raw | SR; teacher's low-resolution head: upsampled raw | SR; the teacher's image) in ``--out``.

The checkpoint (``superres-fit.pt``, ``"format": "lp3d-superres-fit-v1"``) is a plain dict of
tensors and JSON strings (``torch.load(weights_only=True)``); :func:`load_fit` reads it and
``lp3d.training.export --superres`` packages it as ONNX beside the encoder.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lp3d import array_cache
from lp3d.atomic import atomic_path
from lp3d.errors import EXIT_ERROR, run_command
from lp3d.nets.superres import SuperresConfig, SuperResolution
from lp3d.training.camera_sampling import FFHQ_MULTIVIEW, FFHQ_REFERENCE, CameraDistribution, sample_cameras
from lp3d.training.losses import SSIMGradientLoss, ssim

__all__ = [
    "FIT_FORMAT",
    "FitConfig",
    "FitError",
    "FitResult",
    "PairKey",
    "PairSet",
    "StalePairsError",
    "default_pair_cache",
    "fit_superres",
    "load_fit",
    "main",
    "model_fingerprint",
]

#: The ``format`` of a fit checkpoint.
FIT_FORMAT = "lp3d-superres-fit-v1"
#: Bumped when the pairs' layout or meaning changes (old caches are then never reused).
PAIRS_FORMAT = 3
CHECKPOINT_NAME = "superres-fit.pt"
#: What the SR can be trained on (:attr:`FitConfig.train_on`).
TRAIN_ON = ("student", "teacher", "both")


class FitError(ValueError):
    """A fit that cannot run or continue here; the message says what and where."""


class StalePairsError(array_cache.StaleCacheError):
    """A cached pair folder that does not match its key or its recorded digests."""


# --------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FitConfig:
    """Everything that defines a fit (saved in its checkpoint). The defaults fit the shipped model
    (64² raw renders -> 256² images) in about 40 minutes on a 2-core CPU; see the module docstring."""

    #: Training pairs: ``identities`` teacher identities × ``views`` multiview cameras each.
    identities: int = 72
    views: int = 2
    first_seed: int = 100_000
    #: Held-out pairs (one view each), scored at the end.
    heldout_identities: int = 8
    heldout_first_seed: int = 900_000
    #: The SR's input (the raw feature render) and output sides.
    raw_resolution: int = 64
    output_resolution: int = 256
    #: Samples per ray of the raw render and of the teacher's target (``lp3d render``'s default).
    depth_resolution: int = 48
    depth_resolution_importance: int = 48
    #: Samples per ray of the encoder's input image (the CPU recipe's training data used 16 + 16).
    input_depth_resolution: int = 16
    input_depth_resolution_importance: int = 16
    #: Plane resolution of the procedural teacher (its native 256).
    teacher_resolution: int = 256
    camera_seed: int = 0
    #: The network: one SynthesisBlock (×2) per width.
    block_channels: tuple[int, ...] = (64, 32)
    w_dim: int = 32
    #: Training inputs: ``student``, ``teacher`` or ``both`` raw renders (see the module docstring).
    train_on: str = "both"
    #: Optimisation.
    steps: int = 2500
    batch_size: int = 8
    #: Side of a training crop in raw pixels (its target is ``crop · output/raw`` pixels).
    crop: int = 32
    lr: float = 1e-2
    lr_final_factor: float = 0.05
    perceptual_weight: float = 1.0
    seed: int = 0
    checkpoint_every: int = 500

    def __post_init__(self) -> None:
        self.validate()

    @property
    def scale(self) -> int:
        return self.output_resolution // self.raw_resolution

    def superres_config(self) -> SuperresConfig:
        return SuperresConfig(
            name=f"fit-{self.raw_resolution}-{self.output_resolution}",
            input_resolution=self.raw_resolution,
            output_resolution=self.output_resolution,
            block_channels=self.block_channels,
            w_dim=self.w_dim,
            use_noise=False,
        )

    def validate(self) -> None:
        for name in (
            "identities",
            "views",
            "heldout_identities",
            "raw_resolution",
            "output_resolution",
            "depth_resolution",
            "input_depth_resolution",
            "teacher_resolution",
            "w_dim",
            "steps",
            "batch_size",
            "crop",
            "checkpoint_every",
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"FitConfig.{name} must be a positive int, got {v!r}")
        for name in (
            "first_seed",
            "heldout_first_seed",
            "camera_seed",
            "seed",
            "depth_resolution_importance",
            "input_depth_resolution_importance",
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"FitConfig.{name} must be an int >= 0, got {v!r}")
        lo, hi = self.first_seed, self.first_seed + self.identities
        if lo < self.heldout_first_seed + self.heldout_identities and self.heldout_first_seed < hi:
            raise ValueError("FitConfig: the training and held-out seed ranges overlap")
        if self.crop > self.raw_resolution:
            raise ValueError(
                f"FitConfig.crop ({self.crop}) must be <= raw_resolution ({self.raw_resolution})"
            )
        for name in ("lr", "lr_final_factor", "perceptual_weight"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"FitConfig.{name} must be a finite number >= 0, got {v!r}")
        if self.train_on not in TRAIN_ON:
            raise ValueError(f"FitConfig.train_on must be one of {list(TRAIN_ON)}, got {self.train_on!r}")
        self.superres_config()  # sizes: output = raw × 2^k, one width per ×2

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FitConfig:
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"FitConfig.from_dict: unknown keys {unknown}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()})


def model_fingerprint(encoder: Any) -> str:
    """SHA-256 over what the student's renders depend on: the encoder's weights file(s), the decoder
    and the scene bounds (not the sidecar's other fields, so adding an SR entry keeps the cache)."""
    from lp3d.lift.model_package import decoder_digest, file_sha256

    pkg = encoder.package
    h = hashlib.sha256()
    h.update(file_sha256(pkg.model_path).encode())
    h.update(decoder_digest(pkg.decoder).encode())
    h.update(np.array([pkg.box_warp, pkg.ray_start, pkg.ray_end], "<f8").tobytes())
    return h.hexdigest()


# --------------------------------------------------------------------------------------------------
# Pairs: made once, cached on disk
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PairKey:
    """Everything the cached pairs depend on; its hash names the cache folder."""

    model_fingerprint: str
    teacher: str
    teacher_fingerprint: str
    teacher_resolution: int
    #: The teacher's low-resolution head (its raw renders' planes): the student's plane resolution.
    teacher_low_resolution: int
    first_seed: int
    identities: int
    views: int
    image_size: int
    raw_resolution: int
    output_resolution: int
    depth_resolution: int
    depth_resolution_importance: int
    input_depth_resolution: int
    input_depth_resolution_importance: int
    reference_cameras: dict[str, Any]
    multiview_cameras: dict[str, Any]
    camera_seed: int
    #: Also render the student directly at the output size (``direct``; the held-out pairs).
    direct: bool = False
    format: int = PAIRS_FORMAT

    def digest(self) -> str:
        return array_cache.key_digest(asdict(self))

    @property
    def n_pairs(self) -> int:
        return self.identities * self.views

    def shapes(self) -> dict[str, tuple[tuple[int, ...], str]]:
        n, r, o = self.n_pairs, self.raw_resolution, self.output_resolution
        direct = {"direct": ((n, 3, o, o), "float16")} if self.direct else {}
        return {
            **direct,
            "features": ((n, 32, r, r), "float16"),
            "teacher_features": ((n, 32, r, r), "float16"),
            "target": ((n, 3, o, o), "float16"),
            "camera": ((n, 25), "float32"),
            "seed": ((n,), "int64"),
        }


def default_pair_cache() -> Path:
    """``superres-pairs`` inside :func:`lp3d.training.synthetic_data.default_cache_root`."""
    from lp3d.training.synthetic_data import default_cache_root

    return default_cache_root() / "superres-pairs"


def _camera(dist: CameraDistribution, camera_seed: int, stream: int, identity_seed: int) -> np.ndarray:
    """One camera label (25,) float32, a pure function of the seeds (prefix-stable pair sets)."""
    gen = np.random.Generator(np.random.PCG64([camera_seed, stream, identity_seed]))
    labels = sample_cameras(dist, 1, gen).labels
    assert labels is not None
    return labels[0].astype(np.float32)


@dataclass
class PairSet:
    """The arrays of one cached pair set (read into memory) and where they came from."""

    key: PairKey
    path: Path
    features: np.ndarray
    teacher_features: np.ndarray
    target: np.ndarray
    camera: np.ndarray
    seed: np.ndarray
    #: The student rendered directly at the output size (held-out pairs only).
    direct: np.ndarray | None = None

    def __len__(self) -> int:
        return self.key.n_pairs

    @classmethod
    def load(cls, path: str | os.PathLike[str], key: PairKey) -> PairSet:
        """Read and verify a cached folder; :class:`StalePairsError` names what does not match."""
        path = Path(path)
        arrays = array_cache.load(path, asdict(key), key.shapes(), error=StalePairsError)
        return cls(key=key, path=path, **arrays)

    @classmethod
    def open(
        cls,
        key: PairKey,
        encoder: Any,
        teacher: Any,
        *,
        root: str | os.PathLike[str] | None = None,
        progress: bool = True,
    ) -> PairSet:
        """The pairs of ``key`` under ``root``: loaded when cached and valid, else (re)built."""
        root = Path(root) if root is not None else default_pair_cache()
        path = root / f"sr-{key.digest()}"
        return array_cache.load_or_build(
            path,
            lambda: cls.load(path, key),
            lambda: cls.build(key, encoder, teacher, path, progress=progress),
            "cached super-resolution pairs rejected, rebuilding them",
        )

    @staticmethod
    def build(key: PairKey, encoder: Any, teacher: Any, path: Path, *, progress: bool = True) -> Path:
        """Render the pairs of ``key`` into ``path`` (written whole or not at all)."""
        from lp3d.render.native import render_triplane, renderer
        from lp3d.teachers import ProceduralTeacher
        from lp3d.training.synthetic_data import teacher_fingerprint

        if teacher_fingerprint(teacher, key.first_seed) != key.teacher_fingerprint:
            raise StalePairsError("the teacher's fingerprint differs from the pair key's")
        low = ProceduralTeacher(resolution=key.teacher_low_resolution)
        render = renderer().render
        pkg = encoder.package
        ref_dist = CameraDistribution.from_dict(key.reference_cameras)
        mv_dist = CameraDistribution.from_dict(key.multiview_cameras)
        with array_cache.build(path, asdict(key), key.shapes()) as out:
            bar = None
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=key.identities, desc="rendering SR pairs", unit="identity", file=sys.stderr)
            for i in range(key.identities):
                seed = key.first_seed + i
                truth = render_triplane(teacher.sample(seed))
                ref = _camera(ref_dist, key.camera_seed, 0, seed)
                image = render(
                    truth,
                    ref,
                    resolution=key.image_size,
                    depth_resolution=key.input_depth_resolution,
                    depth_resolution_importance=key.input_depth_resolution_importance,
                    outputs=["rgb"],
                )["rgb"]
                planes = encoder.run(image[None].astype(np.float32))[0]
                student = render_triplane(pkg.triplane(planes))
                cams = np.stack([_camera(mv_dist, key.camera_seed, 1 + v, seed) for v in range(key.views)])
                samples = {
                    "depth_resolution": key.depth_resolution,
                    "depth_resolution_importance": key.depth_resolution_importance,
                }
                raw = render(student, cams, resolution=key.raw_resolution, outputs=["features"], **samples)
                own = render(
                    render_triplane(low.sample(seed)),
                    cams,
                    resolution=key.raw_resolution,
                    outputs=["features"],
                    **samples,
                )
                high = render(truth, cams, resolution=key.output_resolution, outputs=["rgb"], **samples)
                lo, hi = i * key.views, (i + 1) * key.views
                if key.direct:
                    out["direct"][lo:hi] = render(
                        student, cams, resolution=key.output_resolution, outputs=["rgb"], **samples
                    )["rgb"]
                out["features"][lo:hi] = raw["features"]
                out["teacher_features"][lo:hi] = own["features"]
                out["target"][lo:hi] = high["rgb"]
                out["camera"][lo:hi] = cams
                out["seed"][lo:hi] = seed
                if bar is not None:
                    bar.update()
            if bar is not None:
                bar.close()
        return path


def pair_keys(cfg: FitConfig, encoder: Any, teacher: Any) -> tuple[PairKey, PairKey]:
    """``(training, held-out)`` pair keys of a fit."""
    from lp3d.training.synthetic_data import teacher_fingerprint

    fingerprint = model_fingerprint(encoder)

    def key(first: int, identities: int, views: int, direct: bool) -> PairKey:
        return PairKey(
            model_fingerprint=fingerprint,
            teacher="procedural",
            teacher_fingerprint=teacher_fingerprint(teacher, first),
            teacher_resolution=cfg.teacher_resolution,
            teacher_low_resolution=encoder.package.triplane_resolution,
            first_seed=first,
            identities=identities,
            views=views,
            image_size=encoder.package.image_size,
            raw_resolution=cfg.raw_resolution,
            output_resolution=cfg.output_resolution,
            depth_resolution=cfg.depth_resolution,
            depth_resolution_importance=cfg.depth_resolution_importance,
            input_depth_resolution=cfg.input_depth_resolution,
            input_depth_resolution_importance=cfg.input_depth_resolution_importance,
            reference_cameras=FFHQ_REFERENCE.to_dict(),
            multiview_cameras=FFHQ_MULTIVIEW.to_dict(),
            camera_seed=cfg.camera_seed,
            direct=direct,
        )

    train = key(cfg.first_seed, cfg.identities, cfg.views, False)
    return train, key(cfg.heldout_first_seed, cfg.heldout_identities, 1, True)


# --------------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------------


def new_superres(cfg: FitConfig) -> SuperResolution:
    """The network a fit starts from: EG3D's initialisation, seeded by ``cfg.seed``, with every ToRGB
    weight zeroed, so that its first output is the FIR-upsampled raw rgb (about what bilinear
    upsampling gives) and training learns the residual detail."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        sr = SuperResolution(cfg.superres_config())
    with torch.no_grad():
        for block in sr.blocks:
            block.torgb.weight.zero_()
    return sr


def synthesize(sr: SuperResolution, features: Tensor) -> Tensor:
    """The SR's blocks on features (B, C, h, w) of any size (crops included; ``SuperResolution.forward``
    would resize them to its input resolution) -> (B, 3, h·scale, w·scale)."""
    x, img = features, features[:, :3]
    w = sr.w_const.to(x.dtype).unsqueeze(0)
    for block in sr.blocks:
        x, img = block(x, img, w)
    return img


def _batch(pairs: PairSet, cfg: FitConfig, step: int) -> tuple[Tensor, Tensor]:
    """Step ``step``'s crops: (B, 32, c, c) features and (B, 3, c·s, c·s) targets, a pure function of
    ``(cfg.seed, step)`` (so a resumed fit draws what the uninterrupted one would). With ``train_on``
    ``both``, the first half of the batch reads the student's raw renders, the rest the teacher's."""
    g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    n, c, s, r, b = len(pairs), cfg.crop, cfg.scale, cfg.raw_resolution, cfg.batch_size
    index = torch.randint(n, (b,), generator=g).tolist()
    offsets = torch.randint(r - c + 1, (b, 2), generator=g).tolist()
    flips = (torch.rand(b, generator=g) < 0.5).tolist()
    if cfg.train_on == "both":
        sources = [pairs.features if k < (b + 1) // 2 else pairs.teacher_features for k in range(b)]
    else:
        sources = [pairs.features if cfg.train_on == "student" else pairs.teacher_features] * b
    xs, ys = [], []
    for i, (oy, ox), flip, feats in zip(index, offsets, flips, sources, strict=True):
        x = torch.from_numpy(feats[i, :, oy : oy + c, ox : ox + c].astype(np.float32))
        y = torch.from_numpy(
            pairs.target[i, :, oy * s : (oy + c) * s, ox * s : (ox + c) * s].astype(np.float32)
        )
        if flip:
            x, y = x.flip(-1), y.flip(-1)
        xs.append(x)
        ys.append(y)
    return torch.stack(xs), torch.stack(ys)


def _lr(cfg: FitConfig, step: int) -> float:
    t = min(step / max(cfg.steps, 1), 1.0)
    return cfg.lr * (cfg.lr_final_factor + (1 - cfg.lr_final_factor) * 0.5 * (1 + math.cos(math.pi * t)))


def psnr(a: Tensor, b: Tensor) -> Tensor:
    """Per-image PSNR (dB) of images (B, 3, H, W) in [-1, 1] (clipped), on the [0, 1] scale."""
    mse = ((a.clamp(-1, 1) - b.clamp(-1, 1)) / 2).square().flatten(1).mean(1)
    return -10 * torch.log10(mse.clamp_min(1e-12))


@torch.no_grad()
def score(sr: SuperResolution, pairs: PairSet) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Held-out scores against the teacher's image: of the SR image and of the bilinearly upsampled raw
    render, for the student's raw renders (``superres_*``, ``bilinear_*``, ``gain_db``) and for the
    teacher's own low-resolution ones (``teacher_*``), and of the student rendered directly at the
    output size (``direct_*``, when the pairs have it: what ``--raw --resolution R_out`` draws); and,
    per pair, a figure row (student: upsampled raw | SR [| direct]; teacher low: upsampled raw | SR;
    teacher's image) as (H, 5W or 6W, 3) uint8."""
    from lp3d.images import rgb_to_uint8

    sr.eval()
    rows: list[np.ndarray] = []
    out: dict[str, list[float]] = {}
    for i in range(len(pairs)):
        y = torch.from_numpy(pairs.target[i : i + 1].astype(np.float32))
        images = []
        for prefix, feats in (("", pairs.features), ("teacher_", pairs.teacher_features)):
            x = torch.from_numpy(feats[i : i + 1].astype(np.float32))
            up = F.interpolate(x[:, :3], size=y.shape[-2:], mode="bilinear", align_corners=False)
            high = sr(x)
            for name, img in (("bilinear", up), ("superres", high)):
                out.setdefault(f"{prefix}{name}_psnr", []).append(float(psnr(img, y)[0]))
                out.setdefault(f"{prefix}{name}_ssim", []).append(float(ssim(img.clamp(-1, 1), y)[0]))
            images += [up, high]
            if not prefix and pairs.direct is not None:
                direct = torch.from_numpy(pairs.direct[i : i + 1].astype(np.float32))
                out.setdefault("direct_psnr", []).append(float(psnr(direct, y)[0]))
                out.setdefault("direct_ssim", []).append(float(ssim(direct.clamp(-1, 1), y)[0]))
                images.append(direct)
        rows.append(np.concatenate([rgb_to_uint8(t[0].numpy()) for t in (*images, y)], axis=1))
    report: dict[str, Any] = {k: float(np.mean(v)) for k, v in out.items()}
    report["gain_db"] = report["superres_psnr"] - report["bilinear_psnr"]
    report["teacher_gain_db"] = report["teacher_superres_psnr"] - report["teacher_bilinear_psnr"]
    report["pairs"] = len(pairs)
    report["per_pair"] = out
    return report, rows


@dataclass
class FitResult:
    """What :func:`fit_superres` made: the network, its checkpoint and the held-out report."""

    superres: SuperResolution
    checkpoint: Path
    report: dict[str, Any]


def _checkpoint(
    sr: SuperResolution,
    opt: torch.optim.Optimizer,
    cfg: FitConfig,
    step: int,
    model: dict[str, Any],
    pairs: dict[str, str],
    report: dict[str, Any] | None,
) -> dict[str, Any]:
    return {
        "format": FIT_FORMAT,
        "fit_config": json.dumps(cfg.to_dict(), sort_keys=True),
        "superres_config": json.dumps(sr.config.to_dict(), sort_keys=True),
        "superres": {k: v.detach().cpu().clone() for k, v in sr.state_dict().items()},
        "optimizer": opt.state_dict(),
        "step": step,
        "model": json.dumps(model, sort_keys=True),
        "pairs": json.dumps(pairs, sort_keys=True),
        "report": json.dumps(report, sort_keys=True),
    }


def _save(ckpt: dict[str, Any], path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(ckpt, tmp)


@dataclass
class LoadedFit:
    """A fit checkpoint read back (:func:`load_fit`)."""

    path: Path
    config: FitConfig
    superres: SuperResolution
    step: int
    model: dict[str, Any]
    report: dict[str, Any] | None
    raw: dict[str, Any]

    @property
    def finished(self) -> bool:
        return self.step >= self.config.steps and self.report is not None


def load_fit(path: str | os.PathLike[str]) -> LoadedFit:
    """Read a fit checkpoint (a folder means its ``superres-fit.pt``); never unpickles code.
    Raises :class:`FitError` naming the file and what is wrong."""
    p = Path(path)
    if p.is_dir():
        p = p / CHECKPOINT_NAME
    if not p.is_file():
        raise FitError(f"{p}: no such super-resolution fit checkpoint")
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for non-checkpoints
        raise FitError(f"{p}: cannot be read as a plain state-dict checkpoint ({e})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FIT_FORMAT:
        got = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise FitError(f"{p}: not a super-resolution fit checkpoint of format {FIT_FORMAT!r} (got {got!r})")
    try:
        cfg = FitConfig.from_dict(json.loads(ckpt["fit_config"]))
        sr_cfg = SuperresConfig.from_dict(json.loads(ckpt["superres_config"]))
        sr = SuperResolution(sr_cfg)
        sr.load_state_dict(ckpt["superres"], strict=True)
        step = int(ckpt["step"])
        model = json.loads(ckpt["model"])
        report = json.loads(ckpt["report"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise FitError(
            f"{p}: malformed fit checkpoint ({type(e).__name__}: {str(e).splitlines()[0]})"
        ) from None
    return LoadedFit(p, cfg, sr.eval(), step, model, report, ckpt)


def fit_superres(
    model: str | os.PathLike[str] | None,
    out: str | os.PathLike[str],
    cfg: FitConfig | None = None,
    *,
    backend: str | None = None,
    cache: str | os.PathLike[str] | None = None,
    progress: bool = True,
) -> FitResult:
    """Fit an SR for ``model`` (default: the shipped model) into ``out``; see the module docstring.
    Resumes ``out/superres-fit.pt`` when it exists for the same configuration and model."""
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
    from lp3d.lift.model_package import decoder_digest
    from lp3d.teachers import ProceduralTeacher

    cfg = cfg or FitConfig()
    model_path = Path(model) if model is not None else DEFAULT_MODEL
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / CHECKPOINT_NAME
    encoder = load_encoder(model_path, backend)  # type: ignore[arg-type]
    pkg = encoder.package
    info = {
        "path": str(model_path.resolve()),
        "fingerprint": model_fingerprint(encoder),
        "decoder_sha256": decoder_digest(pkg.decoder),
        "config_name": pkg.config_name,
        "image_size": pkg.image_size,
        "teacher": "procedural",
    }
    sr = new_superres(cfg)
    opt = torch.optim.Adam(sr.parameters(), lr=cfg.lr, betas=(0.9, 0.99))
    start = 0
    report: dict[str, Any] | None = None
    if ckpt_path.exists():
        done = load_fit(ckpt_path)
        if done.config != cfg:
            changed = [
                f"{k}: {v!r} -> {getattr(cfg, k)!r}"
                for k, v in done.config.to_dict().items()
                if v != cfg.to_dict()[k]
            ]
            raise FitError(
                f"{ckpt_path} was made with another configuration ({'; '.join(changed)}); use another --out"
            )
        if done.model.get("fingerprint") != info["fingerprint"]:
            raise FitError(
                f"{ckpt_path} was fitted for another model ({done.model.get('path')}); use another --out"
            )
        sr.load_state_dict(done.superres.state_dict())
        opt.load_state_dict(done.raw["optimizer"])
        start, report = done.step, done.report
        print(f"resuming {ckpt_path} at step {start} of {cfg.steps}")

    teacher = ProceduralTeacher(resolution=cfg.teacher_resolution)
    train_key, heldout_key = pair_keys(cfg, encoder, teacher)
    t0 = time.perf_counter()
    train = PairSet.open(train_key, encoder, teacher, root=cache, progress=progress)
    heldout = PairSet.open(heldout_key, encoder, teacher, root=cache, progress=progress)
    t_pairs = time.perf_counter() - t0
    pair_info = {"train": str(train.path), "heldout": str(heldout.path)}
    print(
        f"pairs: {len(train)} training ({train_key.identities} identities × {train_key.views} views), "
        f"{len(heldout)} held-out; {cfg.raw_resolution}² raw -> {cfg.output_resolution}²; "
        f"ready in {t_pairs:.0f} s ({train.path.parent})"
    )

    perceptual = SSIMGradientLoss()
    log_path = out / "log.csv"
    new_log = not log_path.exists() or start == 0
    t0 = time.perf_counter()
    if start < cfg.steps:
        sr.train()
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=cfg.steps, initial=start, desc="fitting SR", unit="step", file=sys.stderr)
        with open(log_path, "w" if new_log else "a", newline="") as log_file:
            log = csv.writer(log_file)
            if new_log:
                log.writerow(["step", "loss", "l1", "ssim_grad", "lr", "seconds"])
            for step in range(start, cfg.steps):
                lr = _lr(cfg, step)
                for group in opt.param_groups:
                    group["lr"] = lr
                x, y = _batch(train, cfg, step)
                pred = synthesize(sr, x)
                l1 = (pred - y).abs().mean()
                perc = perceptual(pred, y) if cfg.perceptual_weight > 0 else pred.new_zeros(())
                loss = l1 + cfg.perceptual_weight * perc
                if not torch.isfinite(loss):
                    raise FitError(f"non-finite loss at step {step} (lr {lr:g}); lower --lr")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                done_steps = step + 1
                values = [loss.item(), l1.item(), perc.item()]
                log.writerow(
                    [done_steps, *(f"{v:.5f}" for v in values), f"{lr:.3g}"]
                    + [f"{time.perf_counter() - t0:.1f}"]
                )
                if bar is not None:
                    bar.update()
                    bar.set_postfix_str(f"loss {values[0]:.4f}")
                if done_steps % cfg.checkpoint_every == 0 and done_steps < cfg.steps:
                    log_file.flush()
                    _save(_checkpoint(sr, opt, cfg, done_steps, info, pair_info, None), ckpt_path)
            if bar is not None:
                bar.close()
        report = None
    t_train = time.perf_counter() - t0
    if report is None:
        report, rows = score(sr, heldout)
        report.update(
            {
                "steps": cfg.steps,
                "training_pairs": len(train),
                "train_seconds_this_run": round(t_train, 1),
                "pairs_seconds_this_run": round(t_pairs, 1),
            }
        )
        _save(_checkpoint(sr, opt, cfg, cfg.steps, info, pair_info, report), ckpt_path)
        from lp3d.images import save_png, tile

        save_png(out / "heldout.png", tile(rows[:4], columns=1))
        with atomic_path(out / "report.json") as tmp:
            tmp.write_text(json.dumps({"config": cfg.to_dict(), "model": info, **report}, indent=2) + "\n")
    print(
        f"held-out, the teacher's own low-resolution renders: SR {report['teacher_superres_psnr']:.2f} dB, "
        f"bilinear {report['teacher_bilinear_psnr']:.2f} dB ({report['teacher_gain_db']:+.2f} dB)"
    )
    print(
        f"held-out ({report['pairs']} pairs): SR {report['superres_psnr']:.2f} dB PSNR / SSIM "
        f"{report['superres_ssim']:.3f}; bilinear upsampling of the raw render "
        f"{report['bilinear_psnr']:.2f} dB / {report['bilinear_ssim']:.3f}; gain {report['gain_db']:+.2f} dB"
    )
    if "direct_psnr" in report:
        print(
            f"  (the student rendered directly at {cfg.output_resolution}²: {report['direct_psnr']:.2f} dB / "
            f"{report['direct_ssim']:.3f})"
        )
    if report["gain_db"] <= 0:
        print(
            "warning: the SR does not beat bilinear upsampling on the held-out pairs; do not ship it",
            file=sys.stderr,
        )
    print(f"wrote {ckpt_path}; package it with: lp3d export --superres {ckpt_path} --package MODEL.onnx")
    return FitResult(sr.eval(), ckpt_path, report)


# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The fitting options: one flag per :class:`FitConfig` field, plus the inputs and outputs."""
    defaults = FitConfig()
    p.add_argument(
        "model",
        nargs="?",
        default=None,
        help="MODEL.onnx (with its MODEL.json), CHECKPOINT.pt or a run folder (default: the shipped model)",
    )
    p.add_argument("--out", required=True, type=Path, help="folder for the checkpoint, log.csv, report.json")
    p.add_argument("--backend", choices=("onnx", "torch"), default=None, help="as for lp3d encode")
    p.add_argument(
        "--cache", type=Path, default=None, help=f"pair cache folder (default: {default_pair_cache()})"
    )
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    for f in fields(FitConfig):
        value = getattr(defaults, f.name)
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, tuple):
            p.add_argument(flag, type=int, nargs="+", default=list(value), help=f"(default: {value})")
        elif f.name == "train_on":
            p.add_argument(flag, choices=TRAIN_ON, default=value, help=f"(default: {value})")
        else:
            p.add_argument(flag, type=type(value), default=value, help=f"(default: {value})")


def build_parser(prog: str = "python -m lp3d.training.superres_fit") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0] if __doc__ else None)
    add_arguments(p)
    p.set_defaults(func=run_cli)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.training.superres_fit``; exit status 0, 1 (an error, one line) or 2 (usage), as
    :mod:`lp3d.errors` says."""
    return run_command(build_parser(), argv)


def run_cli(args: argparse.Namespace) -> int:
    """Fit with parsed :func:`add_arguments` options; returns the exit status."""
    if args.threads:
        torch.set_num_threads(args.threads)
    from lp3d.lift.model_package import ModelPackageError

    try:
        cfg = FitConfig.from_dict({f.name: getattr(args, f.name) for f in fields(FitConfig)})
        fit_superres(
            args.model, args.out, cfg, backend=args.backend, cache=args.cache, progress=not args.quiet
        )
    except (FitError, StalePairsError, ModelPackageError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ERROR
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
