"""The pairs a super-resolution fit learns from (step 1 of :mod:`lp3d.superres_fit.fit`), made
once and cached on disk: :class:`PairKey` (everything they depend on; its hash names the folder),
:class:`PairSet` (the arrays, loaded and verified or rendered), :func:`pair_keys` (a fit's training
and held-out keys) and :func:`model_fingerprint`.

Imports lp3d.array_cache, lp3d.training.camera_sampling and lp3d.superres_fit.config; the
renderer, the teachers, lp3d.lift and lp3d.training.synthetic_data inside the functions that use them.
"""

from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d import array_cache
from lp3d.superres_fit.config import FitConfig
from lp3d.training.camera_sampling import FFHQ_MULTIVIEW, FFHQ_REFERENCE, CameraDistribution, sample_cameras

__all__ = [
    "PAIRS_FORMAT",
    "PairKey",
    "PairSet",
    "StalePairsError",
    "default_pair_cache",
    "model_fingerprint",
    "pair_keys",
]

#: Bumped when the pairs' layout or meaning changes (old caches are then never reused).
PAIRS_FORMAT = 3


class StalePairsError(array_cache.StaleCacheError):
    """A cached pair folder that does not match its key or its recorded digests."""


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
        from lp3d.render.native import native_triplane, renderer
        from lp3d.teachers import ProceduralTeacher
        from lp3d.training.synthetic_data import teacher_fingerprint

        if teacher_fingerprint(teacher, key.first_seed) != key.teacher_fingerprint:
            raise StalePairsError("the teacher's fingerprint differs from the pair key's")
        low = ProceduralTeacher(resolution=key.teacher_low_resolution, version=teacher.version)
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
                truth = native_triplane(teacher.sample(seed))
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
                student = native_triplane(pkg.triplane(planes))
                cams = np.stack([_camera(mv_dist, key.camera_seed, 1 + v, seed) for v in range(key.views)])
                samples = {
                    "depth_resolution": key.depth_resolution,
                    "depth_resolution_importance": key.depth_resolution_importance,
                }
                raw = render(student, cams, resolution=key.raw_resolution, outputs=["features"], **samples)
                own = render(
                    native_triplane(low.sample(seed)),
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
