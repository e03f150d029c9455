"""The frozen teacher of a training run as the run uses it (:class:`RunTeacher`): its decoder on the
training device, the scene bounds its heads fill, its renders at the run's settings, its triplanes at
the student's resolution and the cached datasets it makes (the CPU recipe's training set, the
held-out identities). One part of :class:`lp3d.training.trainer.Trainer`, handed to the training
steps (:mod:`lp3d.training.steps`) and the held-out views (:mod:`lp3d.training.heldout`).

May import the modules of :mod:`lp3d.training` before it (``config``, ``student``,
``synthetic_data``, ``teacher_factory``), not ``steps``, ``heldout``, ``trainer`` or ``cli``."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from lp3d.render.triplane import TriplaneData
from lp3d.teachers import Teacher
from lp3d.training.config import TrainConfig
from lp3d.training.student import SceneBounds, render_teacher
from lp3d.training.synthetic_data import DatasetKey, SyntheticDataset, resize_planes
from lp3d.training.teacher_factory import dataset_key

__all__ = ["RunTeacher"]


@dataclass(eq=False)
class RunTeacher:
    """A run's teacher ``teacher`` (named ``name``) at configuration ``config`` on ``device``.

    ``scene``: the bounds of its heads (a resumed run takes its checkpoint's); ``decoder``: its
    decoder's weights on ``device``; ``data_cache``: where its datasets are cached (default
    :func:`lp3d.training.synthetic_data.default_cache_root`); ``progress``: progress bars while one
    is synthesised."""

    teacher: Teacher
    name: str
    config: TrainConfig
    device: torch.device
    scene: SceneBounds
    decoder: list[Tensor]
    data_cache: str | os.PathLike[str] | None = None
    progress: bool = True

    @classmethod
    def of(
        cls,
        teacher: Teacher,
        name: str,
        config: TrainConfig,
        device: torch.device,
        *,
        data_cache: str | os.PathLike[str] | None = None,
        progress: bool = True,
    ) -> RunTeacher:
        """The teacher with the scene bounds of its first held-out head and its decoder on ``device``."""
        scene = SceneBounds.of(teacher.sample(config.eval_seed_start))
        decoder = [torch.as_tensor(a, device=device) for a in teacher.decoder()]
        return cls(teacher, name, config, device, scene, decoder, data_cache, progress)

    def render(
        self, planes: Tensor, cameras: Tensor, *, raw: bool = True, high: bool = True
    ) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        """:func:`lp3d.training.student.render_teacher` of ``planes`` from ``cameras`` in this run."""
        return render_teacher(
            self.teacher, planes, self.decoder, cameras, self.config, self.scene, raw=raw, high=high
        )

    def planes(self, tris: list[TriplaneData]) -> Tensor:
        """The teacher triplanes (B, 3, 32, T, T) of ``tris`` as float32 on the device."""
        return torch.from_numpy(np.stack([t.planes.astype(np.float32) for t in tris])).to(self.device)

    def target_planes(self, planes: Tensor) -> Tensor:
        """Teacher planes at the student's triplane resolution (for L_tri)."""
        return resize_planes(planes, self.config.triplane_resolution)

    def mean_planes(self, n: int) -> Tensor:
        """Mean (3, 32, T, T) of the teacher triplanes of the first ``n`` training seeds, at the
        student's resolution."""
        lo = self.config.train_seeds[0]
        total = None
        for seed in range(lo, lo + n):
            p = self.planes([self.teacher.sample(seed)])
            total = p if total is None else total + p
        assert total is not None
        return self.target_planes(total / n)[0]

    def input_renderer(self) -> Callable[[Tensor, Tensor], Tensor]:
        """The teacher's render of the encoder's input, exactly as the evaluation makes it."""

        def render(planes: Tensor, cameras: Tensor) -> Tensor:
            planes, cameras = planes.to(self.device), cameras.to(self.device, torch.float32)
            _, _, image = self.render(planes, cameras, raw=False)
            assert image is not None
            return image.float().cpu()

        return render

    def dataset_key(self) -> DatasetKey:
        """The cache key of this run's synthetic training dataset (CPU recipe)."""
        return dataset_key(self.config, self.teacher, self.name)

    def open_dataset(
        self, key: DatasetKey | None = None, *, progress: bool | None = None
    ) -> SyntheticDataset:
        """Load the cached dataset ``key`` (default :meth:`dataset_key`), synthesising it first when
        absent or invalid (with a progress bar unless ``progress`` or :attr:`progress` says not)."""
        return SyntheticDataset.open(
            key if key is not None else self.dataset_key(),
            self.teacher,
            self.input_renderer(),
            root=self.data_cache,
            progress=self.progress if progress is None else progress,
        )
