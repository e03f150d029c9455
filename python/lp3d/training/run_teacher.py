"""The frozen teacher of a training run as the run uses it (:class:`RunTeacher`): its decoder on the
training device, the scene bounds its heads fill, its renders at the run's settings, its triplanes at
the student's resolution and the cached datasets it makes (the CPU recipe's training set, the
held-out identities). One part of :class:`lp3d.training.trainer.Trainer`, handed to the training
steps (:mod:`lp3d.training.steps`) and the held-out views (:mod:`lp3d.training.heldout`).

May import the modules of :mod:`lp3d.training` before it (``config``, ``student``,
``synthetic_data``, ``teacher_factory``), not ``steps``, ``heldout``, ``trainer`` or ``cli``."""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from lp3d.errors import UserError
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

    def input_backend(self) -> str:
        """What ``input_renderer("auto")`` renders with: ``"wgsl"`` (``lp3d_render``) for a teacher
        without super-resolution on a CPU run when ``lp3d_render`` has an adapter, else ``"torch"``
        (saying why when ``lp3d_render`` is unusable)."""
        if getattr(self.teacher, "superresolve", None) is not None or self.device.type != "cpu":
            return "torch"
        from lp3d.render import native

        try:
            native.renderer().adapter_info()  # RuntimeError when there is no adapter, not even lavapipe
        except (UserError, RuntimeError) as e:
            print(
                f"note: rendering the inputs with the torch twin, lp3d_render is unusable: {e}",
                file=sys.stderr,
            )
            return "torch"
        return "wgsl"

    def input_renderer(self, backend: str = "auto") -> Callable[[Tensor, Tensor], Tensor]:
        """The teacher's render of the encoder's input, as the evaluation makes it: ``(planes (B, 3,
        32, T, T), cameras (B, 25)) -> images (B, 3, S, S)`` on the CPU.

        ``backend``: ``"torch"``, the torch twin on the run's device (what the evaluation uses);
        ``"wgsl"``, ``lp3d_render`` (a direct volume render only: no teacher super-resolution);
        ``"auto"``, :meth:`input_backend`'s choice. The two are the same EG3D render to float
        rounding (teacher v2 heads at 128² · 16+16: mean difference 2e-6, 99.8% of values within
        1e-4, the largest 3e-3 at a few silhouette pixels where the importance draw rounds
        differently; tests/training/test_cpu_recipe.py), and on lavapipe ``lp3d_render`` is the faster,
        which shortens a CPU dataset's synthesis (bench/history/RESULTS.md, "The dataset's input images
        rendered by lp3d_render")."""
        if backend not in ("auto", "torch", "wgsl"):
            raise ValueError(f"backend must be 'auto', 'torch' or 'wgsl', got {backend!r}")
        if backend == "auto":
            backend = self.input_backend()
        if backend == "wgsl":
            if getattr(self.teacher, "superresolve", None) is not None:
                raise ValueError(
                    "backend 'wgsl' renders directly; this teacher's input image is super-resolved"
                )
            return self._wgsl_input_renderer()

        def render(planes: Tensor, cameras: Tensor) -> Tensor:
            planes, cameras = planes.to(self.device), cameras.to(self.device, torch.float32)
            _, _, image = self.render(planes, cameras, raw=False)
            assert image is not None
            return image.float().cpu()

        return render

    def _wgsl_input_renderer(self) -> Callable[[Tensor, Tensor], Tensor]:
        """:meth:`input_renderer` by ``lp3d_render``: each identity's planes with the run's decoder
        and scene bounds, rendered at the configuration's image size and samples."""
        from lp3d.render import native

        lp3d_render = native.renderer()
        decoder = [d.detach().cpu().numpy().astype(np.float32) for d in self.decoder]
        settings = self.config.render_settings(self.config.image_size)
        bounds = dataclasses.asdict(self.scene)

        def render(planes: Tensor, cameras: Tensor) -> Tensor:
            planes_np = planes.detach().cpu().numpy().astype(np.float32)
            cameras_np = cameras.detach().cpu().numpy().astype(np.float32)
            images = [
                native.render(lp3d_render.Triplane(p, *decoder, **bounds), cam, settings, outputs=["rgb"])[
                    "rgb"
                ]
                for p, cam in zip(planes_np, cameras_np, strict=True)
            ]
            return torch.from_numpy(np.stack(images))

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
