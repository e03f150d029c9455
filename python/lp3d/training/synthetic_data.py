"""A teacher's synthetic training data, made once and cached on disk (the CPU recipe's data source).

Synthesising a batch (teacher triplanes, then volume renders of them) costs more than the student's
whole step on a CPU (``bench/train_profile.py``), and it does not depend on the student. So the CPU
recipe (:data:`lp3d.training.TRAIN_CONFIGS` ``small``/``tiny``) synthesises ``n_identities`` identities
once and reuses them across steps, runs and resumes. Per identity ``i`` (teacher seed
``first_seed + i``):

* ``planes``: the teacher triplane at the student's plane resolution, float16 (3, 32, T, T): the
  target of the triplane-regression loss (a teacher whose planes differ, EG3D's 256², is resampled
  with :func:`resize_planes`, as the paper recipe resamples its L_tri target);
* ``ref_camera`` and ``ref_image``: a camera from the reference distribution and the teacher's render
  from it at the encoder's image size (the encoder's input, float16 (3, S, S) in [-1, 1]).

The render loss's targets are not cached: the trainer renders the cached planes on a few hundred
random rays per identity, which costs about 1/30 of one input image. Cameras are drawn from a
generator seeded by ``(camera_seed, identity seed)``, so a larger dataset starts with the same
identities and views as a smaller one.

**Cache.** The folder name is a hash of :class:`DatasetKey` (teacher fingerprint, seeds, sizes,
cameras, samples per ray), so a change of any of them makes a new dataset rather than reusing a stale
one. ``meta.json`` records the key and each array's shape, dtype and SHA-256; loading checks them
all, and a folder that fails (truncated, edited, another key) is reported and rebuilt, never reused.
A build writes into a private temporary folder and renames it into place when complete (both
:mod:`lp3d.array_cache`, shared with the SR fit's pairs).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lp3d import array_cache
from lp3d.training.camera_sampling import CameraDistribution, sample_cameras

__all__ = [
    "DATASET_FORMAT",
    "DatasetKey",
    "StaleDatasetError",
    "SyntheticDataset",
    "default_cache_root",
    "resize_planes",
    "teacher_fingerprint",
]

DATASET_FORMAT = 1


class StaleDatasetError(array_cache.StaleCacheError):
    """A cached dataset folder that does not match its key or its recorded digests."""


def default_cache_root() -> Path:
    """``$LP3D_DATA_CACHE``, else ``$LP3D_CACHE/datasets``, else ``~/.cache/lp3d/datasets``."""
    if os.environ.get("LP3D_DATA_CACHE"):
        return Path(os.environ["LP3D_DATA_CACHE"])
    if os.environ.get("LP3D_CACHE"):
        return Path(os.environ["LP3D_CACHE"]) / "datasets"
    return Path.home() / ".cache" / "lp3d" / "datasets"


def resize_planes(planes: Tensor, resolution: int) -> Tensor:
    """Triplanes (B, 3, C, H, W) resampled to (B, 3, C, T, T), T = ``resolution``: the student's plane
    size. Returned unchanged when already that size; otherwise bilinear with antialiasing, so a larger
    teacher plane (EG3D's 256² for a 64² student) is averaged down rather than aliased."""
    if planes.ndim != 5 or planes.shape[1] != 3:
        raise ValueError(f"planes must have shape (B, 3, C, H, W), got {tuple(planes.shape)}")
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"resolution must be an int >= 1, got {resolution!r}")
    b, p, c, h, w = planes.shape
    if h == w == resolution:
        return planes
    flat = F.interpolate(
        planes.reshape(b, p * c, h, w), size=(resolution, resolution), mode="bilinear", antialias=True
    )
    return flat.reshape(b, p, c, resolution, resolution)


def teacher_fingerprint(teacher: Any, probe_seed: int) -> str:
    """A digest of what the teacher produces: its decoder weights and the planes of one identity.

    Any change to the teacher's code that changes its output changes the fingerprint, so a dataset
    cached from an older teacher is never reused."""
    h = hashlib.blake2b(digest_size=16)
    for a in teacher.decoder():
        h.update(np.ascontiguousarray(a, dtype=np.float32).tobytes())
    tri = teacher.sample(probe_seed)
    h.update(np.ascontiguousarray(tri.planes, dtype=np.float32).tobytes())
    h.update(np.array([tri.box_warp, tri.ray_start, tri.ray_end], np.float64).tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class DatasetKey:
    """Everything the cached arrays depend on; its hash names the cache folder."""

    teacher: str
    teacher_fingerprint: str
    first_seed: int
    n_identities: int
    image_size: int
    triplane_resolution: int
    depth_resolution: int
    depth_resolution_importance: int
    reference_cameras: dict[str, Any]
    camera_seed: int = 0
    format: int = DATASET_FORMAT

    def digest(self) -> str:
        return array_cache.key_digest(asdict(self))

    def shapes(self) -> dict[str, tuple[tuple[int, ...], str]]:
        n, s, t = self.n_identities, self.image_size, self.triplane_resolution
        return {
            "planes": ((n, 3, 32, t, t), "float16"),
            "ref_camera": ((n, 25), "float32"),
            "ref_image": ((n, 3, s, s), "float16"),
        }


#: ``render(planes (B,3,32,T,T), cameras (B,25)) -> the encoder's input images (B,3,S,S)``, no gradients.
RenderFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class SyntheticDataset:
    """The arrays of one cached dataset (read into memory) and where they came from."""

    key: DatasetKey
    path: Path
    planes: np.ndarray
    ref_camera: np.ndarray
    ref_image: np.ndarray

    def __len__(self) -> int:
        return self.key.n_identities

    # -- loading -----------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | os.PathLike[str], key: DatasetKey) -> SyntheticDataset:
        """Read and verify a cached folder; :class:`StaleDatasetError` names what does not match."""
        path = Path(path)
        arrays = array_cache.load(path, asdict(key), key.shapes(), error=StaleDatasetError)
        return cls(key=key, path=path, **arrays)

    @classmethod
    def open(
        cls,
        key: DatasetKey,
        teacher: Any,
        render: RenderFn,
        *,
        root: str | os.PathLike[str] | None = None,
        progress: bool = True,
        chunk: int = 16,
    ) -> SyntheticDataset:
        """The dataset for ``key`` under ``root``: loaded when cached and valid, else (re)built."""
        root = Path(root) if root is not None else default_cache_root()
        path = root / key.digest()
        return array_cache.load_or_build(
            path,
            lambda: cls.load(path, key),
            lambda: cls.build(key, teacher, render, path, progress=progress, chunk=chunk),
            "cached dataset rejected, rebuilding it",
        )

    # -- building ----------------------------------------------------------------------------------
    @staticmethod
    def build(
        key: DatasetKey,
        teacher: Any,
        render: RenderFn,
        path: Path,
        *,
        progress: bool = True,
        chunk: int = 16,
    ) -> Path:
        """Synthesise the arrays of ``key`` into ``path`` (written whole or not at all)."""
        if teacher_fingerprint(teacher, key.first_seed) != key.teacher_fingerprint:
            raise StaleDatasetError("the teacher's fingerprint differs from the dataset key's")
        with array_cache.build(path, asdict(key), key.shapes()) as out:
            ref_dist = CameraDistribution.from_dict(key.reference_cameras)
            bar = None
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=key.n_identities, desc="synthesising teacher data", unit="identity")
            for lo in range(0, key.n_identities, chunk):
                hi = min(lo + chunk, key.n_identities)
                seeds = [key.first_seed + i for i in range(lo, hi)]
                tris = teacher.sample_batch(seeds)
                planes = torch.from_numpy(np.stack([t.planes.astype(np.float32) for t in tris]))
                ref = np.stack([_camera(ref_dist, key.camera_seed, 0, s) for s in seeds])
                # The encoder's input is the teacher's own render (its planes at their resolution);
                # the stored L_tri target is at the student's.
                ref_image = render(planes, torch.from_numpy(ref))
                out["planes"][lo:hi] = resize_planes(planes, key.triplane_resolution).numpy()
                out["ref_camera"][lo:hi] = ref
                out["ref_image"][lo:hi] = ref_image.numpy()
                if bar is not None:
                    bar.update(hi - lo)
            if bar is not None:
                bar.close()
        return path


def _camera(dist: CameraDistribution, camera_seed: int, stream: int, identity_seed: int) -> np.ndarray:
    """One camera label (25,) float32, a pure function of the seeds (prefix-stable datasets)."""
    gen = np.random.Generator(np.random.PCG64([camera_seed, stream, identity_seed]))
    labels = sample_cameras(dist, 1, gen).labels
    assert labels is not None
    return labels[0].astype(np.float32)
