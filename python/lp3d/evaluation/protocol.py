"""What an evaluation renders and from where: :class:`EvalSettings`, the held-out identities' input
cameras, the truth and ceiling teachers, and the student's and teachers' renders of the novel views.
Used by :mod:`lp3d.evaluation.evaluate`.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lp3d.lift.refine import RefineSettings
from lp3d.render.camera import FFHQ_FOCAL, look_at_camera
from lp3d.teachers import ProceduralTeacher, Teacher
from lp3d.teachers.procedural import RESOLUTION as PROCEDURAL_RESOLUTION
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.config import TrainConfig
from lp3d.training.student import SceneBounds, Student, render_teacher, render_views

#: The input views' yaws are spread evenly over [-INPUT_YAW_RANGE_DEG, +INPUT_YAW_RANGE_DEG].
INPUT_YAW_RANGE_DEG = 35.0

#: (yaw, pitch) in degrees of the novel views, FFHQ intrinsics and radius.
NOVEL_VIEWS: tuple[tuple[float, float], ...] = ((-30.0, 0.0), (0.0, 0.0), (30.0, 0.0), (0.0, 20.0))


@dataclass(frozen=True)
class EvalSettings:
    """What :func:`evaluate` measures; ``baseline_steps = 0`` skips the baseline.

    ``baseline_mean_of`` training identities make the mean triplane (the floor, and the baseline's
    start). ``timing_repeats = 0`` times the single (cold) call. ``figure_identities``: how many of
    the identities the comparison figure shows.
    """

    n_identities: int = 16
    novel_views: tuple[tuple[float, float], ...] = NOVEL_VIEWS
    input_yaw_range_deg: float = INPUT_YAW_RANGE_DEG
    baseline_steps: int = 100
    baseline_lr: float = 0.02
    baseline_mean_of: int = 16
    #: ``lp3d encode --refine``'s fit, scored as the method "refined" (``steps = 0``: skipped).
    refine: RefineSettings = field(default_factory=lambda: RefineSettings(steps=0))
    #: Also score the student's flip-averaged encoding (:mod:`lp3d.lift.flip_average`) as the method
    #: "flip_averaged".
    flip_average: bool = False
    timing_repeats: int = 3
    figure_identities: int = 8
    #: A progress bar (stderr) over identities and baseline fits.
    progress: bool = False

    def __post_init__(self) -> None:
        for name in ("n_identities", "baseline_mean_of"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"EvalSettings.{name} must be a positive int, got {v!r}")
        for name in ("baseline_steps", "timing_repeats", "figure_identities"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"EvalSettings.{name} must be an int >= 0, got {v!r}")
        if not (math.isfinite(self.input_yaw_range_deg) and 0 <= self.input_yaw_range_deg < 90):
            raise ValueError(
                f"EvalSettings.input_yaw_range_deg must be in [0, 90), got {self.input_yaw_range_deg}"
            )
        if not self.novel_views:
            raise ValueError("EvalSettings.novel_views must name at least one view")


def input_yaws(n: int, half_range_deg: float = INPUT_YAW_RANGE_DEG) -> np.ndarray:
    """Input yaws (degrees) of identities 0..n-1: ``linspace(-half_range, +half_range, n)`` (0 for
    n = 1) in a fixed low-discrepancy order (identity i takes the rank of ``frac(i / phi)``), so the
    first few identities of any n already span the range: n = 3 gives -35°, +35°, 0°."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if n == 1:
        return np.zeros(1)
    levels = np.linspace(-half_range_deg, half_range_deg, n)
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    order = np.argsort(np.argsort((np.arange(n) * golden) % 1.0, kind="stable"), kind="stable")
    return levels[order]


def input_camera(cfg: TrainConfig, seed: int, yaw_deg: float) -> tuple[np.ndarray, float]:
    """The input camera label (25,) of identity ``seed`` at ``yaw_deg``, and its pitch (degrees).

    Pitch, roll, radius and intrinsics are drawn from ``cfg.reference_cameras`` with a generator seeded
    by ``seed`` (the same draws as before the yaw was fixed); the yaw is the given one.
    """
    dist = cfg.reference_cameras
    s = sample_cameras(dist, 1, np.random.Generator(np.random.PCG64(seed)), labels=False)
    label = look_at_camera(
        yaw_deg=float(yaw_deg),
        pitch_deg=float(s.pitch_deg[0]),
        roll_deg=float(s.roll_deg[0]),
        radius=float(s.radius[0]),
        lookat=dist.lookat,
        focal=float(s.focal[0]),
        cx=float(s.cx[0]),
        cy=float(s.cy[0]),
    )
    return label, float(s.pitch_deg[0])


def reference_teachers(teacher: Teacher, cfg: TrainConfig) -> tuple[Teacher, Teacher | None]:
    """``(truth, ceiling)`` for the run's ``teacher``: the native-resolution teacher every metric is
    scored against (and the encoder's input is rendered from), and the teacher that builds heads at the
    student's plane resolution, or None when the ceiling is the truth planes resampled (teachers
    without a resolution, e.g. EG3D).

    Procedural: ``ProceduralTeacher(resolution=256)`` and ``ProceduralTeacher(resolution=T)`` (the
    given teacher is reused where its resolution fits). Others: ``(teacher, None)``.
    """
    if isinstance(teacher, ProceduralTeacher):
        t = cfg.triplane_resolution
        truth = (
            teacher
            if teacher.resolution == PROCEDURAL_RESOLUTION
            else ProceduralTeacher(PROCEDURAL_RESOLUTION, version=teacher.version)
        )
        ceiling = (
            teacher if teacher.resolution == t else ProceduralTeacher(resolution=t, version=teacher.version)
        )
        return truth, ceiling
    return teacher, None


def resample_planes(planes: Tensor, t: int) -> Tensor:
    """Planes (B, 3, C, H, W) at t² (bilinear, antialiased; as ``RunTeacher.target_planes``)."""
    if planes.shape[-1] == t and planes.shape[-2] == t:
        return planes
    b, p, c, h, w = planes.shape
    flat = F.interpolate(planes.reshape(b, p * c, h, w), size=(t, t), mode="bilinear", antialias=True)
    return flat.reshape(b, p, c, t, t)


def planes_tensor(tri: Any, device: torch.device) -> Tensor:
    return torch.from_numpy(np.asarray(tri.planes, np.float32)).unsqueeze(0).to(device)


def novel_view_cameras(settings: EvalSettings, device: torch.device) -> Tensor:
    cams = [look_at_camera(yaw_deg=y, pitch_deg=p, focal=FFHQ_FOCAL) for y, p in settings.novel_views]
    return torch.tensor(np.stack(cams), dtype=torch.float32, device=device)


def render_student(student: Student, planes: Tensor, cams: Tensor) -> dict[str, Tensor]:
    """planes (1, 3, 32, T, T) seen from cams (V, 25) by ``student.render``: ``high`` (V,3,S,S) (its
    final image: super-resolved, or a direct volume render for the CPU recipe), ``raw`` (V,3,r,r),
    ``depth`` (V,r,r)."""
    v = cams.shape[0]
    out = student.render(planes.expand(v, -1, -1, -1, -1), cams)
    return {"high": out.high, "raw": out.features[:, :3], "depth": out.depth}


def render_truth(
    teacher: Teacher,
    planes: Tensor,
    decoder: Sequence[Tensor],
    cams: Tensor,
    cfg: TrainConfig,
    scene: SceneBounds,
) -> dict[str, Tensor]:
    """The teacher's ``high``, ``raw``, ``depth`` and ``weights_sum`` for planes (1, ...) and cams (V, 25)."""
    v = cams.shape[0]
    expanded = planes.expand(v, -1, -1, -1, -1)
    with torch.no_grad():
        out = render_views(expanded, decoder, cams, cfg, scene)
        _, _, high = render_teacher(teacher, expanded, decoder, cams, cfg, scene, raw=False)
    assert high is not None
    return {"high": high, "raw": out["rgb"], "depth": out["depth"], "weights_sum": out["weights_sum"]}


def sync_device(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Any, device: torch.device, repeats: int) -> tuple[Any, float]:
    """``(result, median seconds)`` of ``fn()`` over ``repeats`` runs after one warm-up (``repeats``
    = 0: the time of that one call)."""
    sync_device(device)
    t0 = time.perf_counter()
    result = fn()
    sync_device(device)
    times = [time.perf_counter() - t0]
    if repeats > 0:
        times = []
        for _ in range(repeats):
            sync_device(device)
            t0 = time.perf_counter()
            result = fn()
            sync_device(device)
            times.append(time.perf_counter() - t0)
    return result, statistics.median(times)
