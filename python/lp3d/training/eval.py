"""Evaluate a trained encoder on held-out teacher identities: does it follow its input, and how does it
compare with the mean head, the teacher itself and a per-identity optimisation baseline?

``lp3d eval runs/t/checkpoints/step-000200.pt`` writes ``report.json`` and ``comparison.png``
into ``--out`` (default: ``<run>/eval-step-NNNNNN``) and prints a short table.

Protocol (paper §4 measures novel-view quality and depth on real data; here the teacher is the ground
truth, so every quantity is exact):

* **truth**: the teacher at its *native* plane resolution. For the procedural teacher that is
  ``ProceduralTeacher(resolution=256)`` (its ``RESOLUTION``), whatever resolution the run trained
  against; for EG3D, the teacher's planes as sampled. Every metric of every method (student,
  baseline, floor, ceiling) is against this truth, and the encoder's input image is rendered from it
  too, as a photo of the head would be;
* identities: ``n_identities`` (default 16) teacher seeds ``eval_seed_start + i``, disjoint from the
  training range;
* input view: one camera per identity from the training reference distribution (augmented
  intrinsics, pitch, roll and radius drawn from a generator seeded by the identity seed, so every run
  sees the same inputs), except the yaw, which is set deliberately so that the inputs cover the
  range: the n yaws are spread evenly over [-35°, +35°] (:func:`input_yaws`; 0° for one identity) and
  assigned in a fixed low-discrepancy order, so any first few identities already span the range. Each
  identity's input yaw and pitch are in the report;
* novel views: fixed FFHQ cameras at yaw -30°, 0°, +30° (pitch 0) and pitch +20° (yaw 0);
* image metrics on the final ``image_size``² images (the student's ``Student.render(...).high``:
  super-resolved for the paper recipe, a direct volume render for the CPU recipe): PSNR, SSIM and,
  when its backbone weights exist on disk, LPIPS (AlexNet, the usual metric); PSNR also on the raw
  renders (the first three feature channels);
* depth (supplement "H3DS"): scale-and-shift-invariant L1 and RMSE on the raw depth maps, with the
  truth's depth normalised to [0, 1] over pixels it covers (weights_sum > 0.5), the prediction's
  aligned to it by least squares;
* **identity specificity**: each method's novel views of identity i are scored against its own truth
  (``novel_psnr``, ``novel_ssim``: "own") and against the truth renders of the same views of every
  other held-out identity j != i, averaged over j (``novel_psnr_other``, ``novel_ssim_other``,
  ``novel_psnr_raw_other``). ``identity_specificity_db`` = own - other PSNR (and
  ``identity_specificity_ssim``): 0 for a model that ignores its input (exactly 0 on average for one
  that outputs the same head for every input), large when the renders follow the input's identity;
* **floor** (the mean head): the mean of ``baseline_mean_of`` training identities' teacher triplanes
  at the student's plane resolution, rendered by the run's teacher, scored against every identity;
* **ceiling**: the teacher's own head of each identity at the student's plane resolution, rendered by
  the run's teacher: ``ProceduralTeacher(resolution=triplane_resolution)`` for the procedural teacher;
  for other teachers the truth planes resampled to that resolution (bilinear, antialiased, as the
  trainer's triplane targets). What a perfect encoder of that resolution would reach;
* timing: the encoder's forward (one image) and one view's render (``Student.render``), medians.

Baseline ("like GAN-inversion baselines", e.g. EG3D-PTI): per identity, a triplane fitted to the input
view alone by Adam on L1 (raw and high) plus the run's perceptual loss, through the student's own
renderer (``Student.render``: decoder, and SR when it has one; frozen), starting from the floor's mean
triplane (the analogue of GAN inversion's start at the mean latent). It optimises the triplane
directly, which is less constrained than a generator's latent space; it shows what the encoder buys:
accuracy against time.

``report.json``: run facts, ``identity_seeds``, ``input_yaw_deg``, ``per_identity`` (per seed: input
yaw and pitch, own/other PSNR and SSIM, specificity, floor, ceiling and, when run, baseline PSNR), the
averages per method under ``student``, ``baseline``, ``floor`` and ``ceiling``, and the student's
``identity_specificity_db`` at the top level. ``comparison.png`` shows, for the first
``figure_identities`` (default 8) identities, rows teacher (input, then the novel views), student,
baseline (when run) and ceiling (novel views only).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.errors import EXIT_ERROR, UsageError, run_command
from lp3d.images import rgb_to_uint8, save_png, tile
from lp3d.render.camera import FFHQ_FOCAL, look_at_camera
from lp3d.teachers import ProceduralTeacher, Teacher
from lp3d.teachers.procedural import RESOLUTION as PROCEDURAL_RESOLUTION
from lp3d.training.camera_sampling import sample_cameras
from lp3d.training.checkpoint import load_checkpoint, student_from_checkpoint
from lp3d.training.config import TrainConfig
from lp3d.training.losses import LPIPSLoss, LPIPSWeightsNotFound, build_perceptual, l1, ssim
from lp3d.training.student import SceneBounds, Student, render_teacher, render_views
from lp3d.training.teacher_factory import build_teacher, resolve_teacher_args

__all__ = [
    "INPUT_YAW_RANGE_DEG",
    "NOVEL_VIEWS",
    "EvalSettings",
    "comparison_figure",
    "depth_errors",
    "evaluate",
    "figure_labels",
    "input_camera",
    "input_yaws",
    "main",
    "psnr",
    "reference_teachers",
    "summary_table",
    "write_outputs",
]

#: (yaw, pitch) in degrees of the novel views, FFHQ intrinsics and radius.
NOVEL_VIEWS: tuple[tuple[float, float], ...] = ((-30.0, 0.0), (0.0, 0.0), (30.0, 0.0), (0.0, 20.0))
#: The input views' yaws are spread evenly over [-INPUT_YAW_RANGE_DEG, +INPUT_YAW_RANGE_DEG].
INPUT_YAW_RANGE_DEG = 35.0


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


# --------------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------------


def psnr(a: Tensor, b: Tensor) -> Tensor:
    """Per-image PSNR (dB) of images (B, C, H, W) in [-1, 1] (peak-to-peak 2) -> (B,)."""
    mse = (a.clamp(-1, 1) - b.clamp(-1, 1)).square().flatten(1).mean(dim=1)
    return 10.0 * torch.log10(4.0 / mse.clamp_min(1e-12))


def depth_errors(pred: Tensor, target: Tensor, mask: Tensor) -> tuple[float, float]:
    """Scale-and-shift-invariant ``(L1, RMSE)`` of one depth map pair (H, W) over ``mask`` (H, W) bool.

    The target is normalised to [0, 1] over the mask (supplement "H3DS"), then ``a * pred + b`` is
    fitted to it by least squares and the residual measured. NaN when the mask has < 2 pixels.
    """
    m = mask.flatten()
    if int(m.sum()) < 2:
        return math.nan, math.nan
    p = pred.flatten()[m].double()
    g = target.flatten()[m].double()
    g = (g - g.min()) / (g.max() - g.min()).clamp_min(1e-12)
    design = torch.stack([p, torch.ones_like(p)], dim=1)
    coef = torch.linalg.lstsq(design, g.unsqueeze(1)).solution
    r = design @ coef - g.unsqueeze(1)
    return float(r.abs().mean()), float(r.square().mean().sqrt())


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else None


# --------------------------------------------------------------------------------------------------
# Cameras and reference teachers
# --------------------------------------------------------------------------------------------------


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
            else ProceduralTeacher(PROCEDURAL_RESOLUTION)
        )
        ceiling = teacher if teacher.resolution == t else ProceduralTeacher(resolution=t)
        return truth, ceiling
    return teacher, None


def _resample_planes(planes: Tensor, t: int) -> Tensor:
    """Planes (B, 3, C, H, W) at t² (bilinear, antialiased; as ``Trainer._teacher_target_planes``)."""
    if planes.shape[-1] == t and planes.shape[-2] == t:
        return planes
    b, p, c, h, w = planes.shape
    flat = F.interpolate(planes.reshape(b, p * c, h, w), size=(t, t), mode="bilinear", antialias=True)
    return flat.reshape(b, p, c, t, t)


def _planes(tri: Any, device: torch.device) -> Tensor:
    return torch.from_numpy(np.asarray(tri.planes, np.float32)).unsqueeze(0).to(device)


# --------------------------------------------------------------------------------------------------
# Rendering helpers
# --------------------------------------------------------------------------------------------------


def _views(settings: EvalSettings, device: torch.device) -> Tensor:
    cams = [look_at_camera(yaw_deg=y, pitch_deg=p, focal=FFHQ_FOCAL) for y, p in settings.novel_views]
    return torch.tensor(np.stack(cams), dtype=torch.float32, device=device)


def _render_student(student: Student, planes: Tensor, cams: Tensor) -> dict[str, Tensor]:
    """planes (1, 3, 32, T, T) seen from cams (V, 25) by ``student.render``: ``high`` (V,3,S,S) (its
    final image: super-resolved, or a direct volume render for the CPU recipe), ``raw`` (V,3,r,r),
    ``depth`` (V,r,r)."""
    v = cams.shape[0]
    out = student.render(planes.expand(v, -1, -1, -1, -1), cams)
    return {"high": out.high, "raw": out.features[:, :3], "depth": out.depth}


def _render_truth(
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


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn: Any, device: torch.device, repeats: int) -> tuple[Any, float]:
    """``(result, median seconds)`` of ``fn()`` over ``repeats`` runs after one warm-up (``repeats``
    = 0: the time of that one call)."""
    _sync(device)
    t0 = time.perf_counter()
    result = fn()
    _sync(device)
    times = [time.perf_counter() - t0]
    if repeats > 0:
        times = []
        for _ in range(repeats):
            _sync(device)
            t0 = time.perf_counter()
            result = fn()
            _sync(device)
            times.append(time.perf_counter() - t0)
    return result, statistics.median(times)


# --------------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------------


class _Metrics:
    """Accumulates per-view metrics of one method."""

    def __init__(self) -> None:
        self.values: dict[str, list[float]] = {}

    def add(
        self, prefix: str, pred: dict[str, Tensor], truth: dict[str, Tensor], lpips: LPIPSLoss | None
    ) -> None:
        def put(name: str, vals: Tensor | Sequence[float]) -> None:
            self.values.setdefault(f"{prefix}_{name}", []).extend(float(v) for v in vals)

        put("psnr", psnr(pred["high"], truth["high"]))
        put("psnr_raw", psnr(pred["raw"], truth["raw"]))
        put("ssim", ssim(pred["high"].clamp(-1, 1), truth["high"].clamp(-1, 1)))
        if lpips is not None:
            put("lpips", lpips.distance(pred["high"].clamp(-1, 1), truth["high"].clamp(-1, 1)))
        l1s, rmses = [], []
        for i in range(pred["depth"].shape[0]):
            a, b = depth_errors(pred["depth"][i], truth["depth"][i], truth["weights_sum"][i] > 0.5)
            l1s.append(a)
            rmses.append(b)
        put("depth_l1", l1s)
        put("depth_rmse", rmses)

    def summary(self) -> dict[str, float | None]:
        return {k: _mean(v) for k, v in sorted(self.values.items())}


@dataclass
class _Cross:
    """Novel-view scores of one method's renders of identity i (rows) against the truth of identity j
    (columns), each the mean over the views: PSNR (high and raw) and SSIM, (n, n) arrays."""

    psnr: np.ndarray
    psnr_raw: np.ndarray
    ssim: np.ndarray

    @classmethod
    def of(cls, high: Sequence[Tensor], raw: Sequence[Tensor], truth: Sequence[dict[str, Tensor]]) -> _Cross:
        """``high``/``raw``: one method's renders per identity, or one render for all (the floor)."""
        n = len(truth)
        rows = len(high)
        out = {k: np.zeros((rows, n)) for k in ("psnr", "psnr_raw", "ssim")}
        for i in range(rows):
            h = high[i].clamp(-1, 1)
            for j in range(n):
                t = truth[j]
                out["psnr"][i, j] = float(psnr(h, t["high"]).mean())
                out["psnr_raw"][i, j] = float(psnr(raw[i], t["raw"]).mean())
                out["ssim"][i, j] = float(ssim(h, t["high"].clamp(-1, 1)).mean())
        if rows == 1:  # the same render for every identity
            out = {k: np.repeat(v, n, axis=0) for k, v in out.items()}
        return cls(**out)

    @staticmethod
    def _own_other(m: np.ndarray) -> tuple[list[float], list[float | None]]:
        n = m.shape[0]
        own = [float(m[i, i]) for i in range(n)]
        other = [float((m[i].sum() - m[i, i]) / (n - 1)) if n > 1 else None for i in range(n)]
        return own, other

    def per_identity(self) -> list[dict[str, float | None]]:
        """Per identity: own, other and specificity (own - other) for PSNR, raw PSNR and SSIM."""
        rows: list[dict[str, float | None]] = [{} for _ in range(self.psnr.shape[0])]
        for name, m, spec in (
            ("novel_psnr", self.psnr, "identity_specificity_db"),
            ("novel_psnr_raw", self.psnr_raw, "identity_specificity_raw_db"),
            ("novel_ssim", self.ssim, "identity_specificity_ssim"),
        ):
            own, other = self._own_other(m)
            for row, a, b in zip(rows, own, other, strict=True):
                row[name] = a
                row[f"{name}_other"] = b
                row[spec] = None if b is None else a - b
        return rows

    def summary(self) -> dict[str, float | None]:
        """Averages over identities of the "other" scores and of the specificities."""
        rows = self.per_identity()
        keys = (
            "novel_psnr_other",
            "novel_psnr_raw_other",
            "novel_ssim_other",
            "identity_specificity_db",
            "identity_specificity_raw_db",
            "identity_specificity_ssim",
        )
        return {k: _mean([r[k] for r in rows]) for k in keys}


def _mean_triplane(teacher: Teacher, cfg: TrainConfig, n: int, device: torch.device) -> Tensor:
    """Mean of ``n`` training identities' teacher planes at the student's resolution (1, 3, 32, T, T)."""
    lo = cfg.train_seeds[0]
    planes = np.mean([teacher.sample(lo + i).planes.astype(np.float32) for i in range(n)], axis=0)
    t = torch.from_numpy(planes).unsqueeze(0).to(device)
    return _resample_planes(t, cfg.triplane_resolution)


def fit_triplane(
    student: Student,
    init: Tensor,
    camera: Tensor,
    target_high: Tensor,
    target_raw: Tensor,
    *,
    steps: int,
    lr: float,
    perceptual: nn.Module | None,
    on_step: Callable[[], Any] | None = None,
) -> Tensor:
    """The baseline: planes (1, 3, 32, T, T) fitted to one view by Adam through ``student.render``
    (decoder, and SR when the student has one), the student's parameters frozen."""
    planes = init.clone().requires_grad_(True)
    opt = torch.optim.Adam([planes], lr=lr)
    # A student without SR (CPU recipe) draws its final image by volume rendering the same planes
    # at a higher resolution: the raw render carries the same information at a quarter of the cost.
    raw_only = student.config.recipe == "cpu"
    for _ in range(steps):
        if raw_only:
            raw = render_views(planes, student.decoder.weights(), camera, student.config, student.scene)[
                "rgb"
            ]
            pairs = [(raw, target_raw)]
        else:
            out = _render_student(student, planes, camera)
            pairs = [(out["raw"], target_raw), (out["high"], target_high)]
        loss = sum(l1(a, b) + (perceptual(a, b) if perceptual is not None else 0.0) for a, b in pairs)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if on_step is not None:
            on_step()
    return planes.detach()


def evaluate(
    student: Student,
    teacher: Teacher,
    *,
    settings: EvalSettings | None = None,
    lpips: LPIPSLoss | None = None,
    perceptual: nn.Module | None = None,
    device: str | torch.device = "cpu",
) -> tuple[dict[str, Any], list[list[list[np.ndarray]]]]:
    """Measure ``student`` (and the baseline, the floor and the ceiling) on held-out identities.

    ``teacher`` is the run's (training) teacher; the truth is its native-resolution counterpart
    (:func:`reference_teachers`). ``student.encode(image (1,3,S,S)) -> planes (1,3,32,T,T)`` and
    ``student.render`` are all that is used of the student (with ``config``, ``scene`` and its
    parameters), so a subclass overriding ``encode`` evaluates any image-to-triplane mapping.

    Returns:
        ``(report, rows)``: the JSON-ready report (see the module docstring) and, for the first
        ``settings.figure_identities`` identities, image rows (H, W, 3) uint8 for the comparison
        figure: teacher (input, novel views), student, baseline (when run), ceiling (a blank input
        cell, then the novel views).
    """
    settings = settings or EvalSettings()
    device = torch.device(device)
    # Evaluate in eval mode without parameter gradients, and leave the student as it was.
    was_training = student.training
    flags = [p.requires_grad for p in student.parameters()]
    student.to(device).eval().requires_grad_(False)
    try:
        return _evaluate(student, teacher, settings, lpips, perceptual, device)
    finally:
        student.train(was_training)
        for p, flag in zip(student.parameters(), flags, strict=True):
            p.requires_grad_(flag)


def _evaluate(
    student: Student,
    teacher: Teacher,
    settings: EvalSettings,
    lpips: LPIPSLoss | None,
    perceptual: nn.Module | None,
    device: torch.device,
) -> tuple[dict[str, Any], list[list[list[np.ndarray]]]]:
    cfg = student.config
    scene = student.scene
    t_res = cfg.triplane_resolution
    truth_teacher, ceiling_teacher = reference_teachers(teacher, cfg)
    truth_dec = [torch.as_tensor(a, device=device) for a in truth_teacher.decoder()]
    run_dec = [torch.as_tensor(a, device=device) for a in teacher.decoder()]
    views = _views(settings, device)
    n = settings.n_identities
    seeds = [cfg.eval_seed_start + i for i in range(n)]
    yaws = [float(y) for y in input_yaws(n, settings.input_yaw_range_deg)]
    methods = ("student", "baseline", "floor", "ceiling")
    metrics = {m: _Metrics() for m in methods}
    # Per method and identity: the novel views' final and raw renders (for the cross-identity scores).
    high: dict[str, list[Tensor]] = {m: [] for m in methods}
    raw: dict[str, list[Tensor]] = {m: [] for m in methods}
    truths: list[dict[str, Tensor]] = []
    pitches: list[float] = []
    encode_s: list[float] = []
    render_s: list[float] = []
    fit_s: list[float] = []
    rows: list[list[list[np.ndarray]]] = []
    truth_resolution = None

    # The floor: the mean head, one render for every identity (and the baseline's start).
    mean_planes = _mean_triplane(teacher, cfg, settings.baseline_mean_of, device)
    floor_nv = _render_truth(teacher, mean_planes, run_dec, views, cfg, scene)
    high["floor"].append(floor_nv["high"])
    raw["floor"].append(floor_nv["raw"])
    run_baseline = settings.baseline_steps > 0

    def to_u8(x: Tensor) -> np.ndarray:
        return rgb_to_uint8(x.detach().cpu().numpy())

    bar = None
    if settings.progress:
        from tqdm import tqdm

        bar = tqdm(total=n * (1 + settings.baseline_steps), desc="eval", unit="step", file=sys.stderr)
    for k, seed in enumerate(seeds):
        if bar is not None:
            bar.set_postfix_str(f"identity seed {seed}")
        planes_t = _planes(truth_teacher.sample(seed), device)
        truth_resolution = int(planes_t.shape[-1])
        label, pitch = input_camera(cfg, seed, yaws[k])
        pitches.append(pitch)
        cam = torch.from_numpy(label).float().unsqueeze(0).to(device)
        truth_in = _render_truth(truth_teacher, planes_t, truth_dec, cam, cfg, scene)
        truth_nv = _render_truth(truth_teacher, planes_t, truth_dec, views, cfg, scene)
        truths.append(truth_nv)
        image = truth_in["high"]

        with torch.no_grad():
            planes_s, t_enc = _timed(
                lambda image=image: student.encode(image), device, settings.timing_repeats
            )
            pred_in, t_ren = _timed(
                lambda p=planes_s, c=cam: _render_student(student, p, c), device, settings.timing_repeats
            )
            pred_nv = _render_student(student, planes_s, views)
        encode_s.append(t_enc)
        render_s.append(t_ren)
        metrics["student"].add("input", pred_in, truth_in, lpips)
        metrics["student"].add("novel", pred_nv, truth_nv, lpips)
        high["student"].append(pred_nv["high"])
        raw["student"].append(pred_nv["raw"])
        metrics["floor"].add("novel", floor_nv, truth_nv, lpips)

        # The ceiling: the teacher's own head at the student's plane resolution.
        if ceiling_teacher is not None:
            planes_c = _planes(ceiling_teacher.sample(seed), device)
        else:
            planes_c = _resample_planes(planes_t, t_res)
        ceil_nv = _render_truth(teacher, planes_c, run_dec, views, cfg, scene)
        metrics["ceiling"].add("novel", ceil_nv, truth_nv, lpips)
        high["ceiling"].append(ceil_nv["high"])
        raw["ceiling"].append(ceil_nv["raw"])

        show = k < settings.figure_identities
        figure = []
        if show:
            figure = [
                [to_u8(image[0])] + [to_u8(v) for v in truth_nv["high"]],
                [to_u8(pred_in["high"][0])] + [to_u8(v) for v in pred_nv["high"]],
            ]

        if run_baseline:
            t0 = time.perf_counter()
            with torch.enable_grad():
                planes_b = fit_triplane(
                    student,
                    mean_planes,
                    cam,
                    truth_in["high"],
                    truth_in["raw"],
                    steps=settings.baseline_steps,
                    lr=settings.baseline_lr,
                    perceptual=perceptual,
                    on_step=None if bar is None else bar.update,
                )
            _sync(device)
            fit_s.append(time.perf_counter() - t0)
            with torch.no_grad():
                base_in = _render_student(student, planes_b, cam)
                base_nv = _render_student(student, planes_b, views)
            metrics["baseline"].add("input", base_in, truth_in, lpips)
            metrics["baseline"].add("novel", base_nv, truth_nv, lpips)
            high["baseline"].append(base_nv["high"])
            raw["baseline"].append(base_nv["raw"])
            if show:
                figure.append([to_u8(base_in["high"][0])] + [to_u8(v) for v in base_nv["high"]])
        if show:
            blank = np.full_like(figure[0][0], 24)
            figure.append([blank] + [to_u8(v) for v in ceil_nv["high"]])
            rows.append(figure)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()

    done = [m for m in methods if high[m]]
    cross = {m: _Cross.of(high[m], raw[m], truths) for m in done}
    per_method = {m: cross[m].per_identity() for m in done}
    per_identity: list[dict[str, Any]] = []
    for k, seed in enumerate(seeds):
        s = per_method["student"][k]
        row: dict[str, Any] = {
            "seed": seed,
            "input_yaw_deg": yaws[k],
            "input_pitch_deg": pitches[k],
            **{
                key: s[key]
                for key in (
                    "novel_psnr",
                    "novel_psnr_other",
                    "identity_specificity_db",
                    "novel_ssim",
                    "novel_ssim_other",
                    "identity_specificity_ssim",
                )
            },
            "floor_novel_psnr": per_method["floor"][k]["novel_psnr"],
            "ceiling_novel_psnr": per_method["ceiling"][k]["novel_psnr"],
        }
        if run_baseline:
            b = per_method["baseline"][k]
            row["baseline_novel_psnr"] = b["novel_psnr"]
            row["baseline_identity_specificity_db"] = b["identity_specificity_db"]
        per_identity.append(row)

    student_summary = {**metrics["student"].summary(), **cross["student"].summary()}
    report: dict[str, Any] = {
        "config": cfg.name,
        "identity_seeds": seeds,
        "input_yaw_deg": yaws,
        "input_pitch_deg": pitches,
        "novel_views_yaw_pitch_deg": [list(v) for v in settings.novel_views],
        "image_size": cfg.image_size,
        "raw_resolution": cfg.raw_resolution,
        "triplane_resolution": t_res,
        "truth": {
            "teacher": type(truth_teacher).__name__,
            "plane_resolution": truth_resolution,
            "note": "every metric is against this teacher at its native plane resolution; the encoder's "
            "input is rendered from it too",
        },
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "lpips": None if lpips is None else {"net": lpips.net, "weights": lpips.weights_path},
        "identity_specificity_db": student_summary["identity_specificity_db"],
        "student": {
            **student_summary,
            "encode_ms": 1000 * statistics.median(encode_s),
            "render_ms": 1000 * statistics.median(render_s),
        },
        "floor": {
            "method": f"the mean of {settings.baseline_mean_of} training identities' teacher triplanes at "
            f"{t_res}², rendered by the run's teacher (the same head for every input)",
            "mean_of": settings.baseline_mean_of,
            **metrics["floor"].summary(),
            **cross["floor"].summary(),
        },
        "ceiling": {
            "method": (
                f"the teacher's own head built at {t_res}² "
                f"({type(ceiling_teacher).__name__}(resolution={t_res}))"
                if ceiling_teacher is not None
                else f"the teacher's planes resampled to {t_res}² (bilinear, antialiased)"
            )
            + ", rendered by the run's teacher",
            "plane_resolution": t_res,
            **metrics["ceiling"].summary(),
            **cross["ceiling"].summary(),
        },
        "per_identity": per_identity,
    }
    if run_baseline:
        report["baseline"] = {
            "method": "per-identity triplane optimisation (Adam) on the input view, from the mean triplane",
            "steps": settings.baseline_steps,
            "lr": settings.baseline_lr,
            **metrics["baseline"].summary(),
            **cross["baseline"].summary(),
            "fit_s": statistics.median(fit_s),
            "render_ms": 1000 * statistics.median(render_s),
        }
    return report, rows


# --------------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------------


def comparison_figure(
    rows: list[list[list[np.ndarray]]],
    labels: Sequence[str],
    *,
    notes: Sequence[str] | None = None,
    title: str | None = None,
    max_tile: int = 256,
) -> np.ndarray:
    """One image: per identity, one row per method (``labels``), with the label at the left.

    ``notes``: one line per identity, drawn under its first label (e.g. the input yaw). ``title``: a
    line above the grid. Tiles larger than ``max_tile`` pixels are downscaled to keep the image small.
    """
    from PIL import Image, ImageDraw

    flat = [img for identity in rows for row in identity for img in row]
    if flat[0].shape[0] > max_tile:
        size = (max_tile * flat[0].shape[1] // flat[0].shape[0], max_tile)
        flat = [np.asarray(Image.fromarray(img).resize(size, Image.Resampling.LANCZOS)) for img in flat]
    columns = len(rows[0][0])
    grid = tile(flat, columns)
    margin = 80
    top = 16 if title else 0
    canvas = Image.new("RGB", (grid.shape[1] + margin, grid.shape[0] + top), (24, 24, 24))
    canvas.paste(Image.fromarray(grid), (margin, top))
    draw = ImageDraw.Draw(canvas)
    if title:
        draw.text((4, 2), title, fill=(230, 230, 230))
    h = flat[0].shape[0]
    r = 0
    for k, identity in enumerate(rows):
        for i, _ in enumerate(identity):
            y = top + 2 + r * (h + 2) + h // 2 - 6
            draw.text((4, y), labels[i], fill=(230, 230, 230))
            if i == 0 and notes is not None:
                draw.text((4, y + 12), notes[k], fill=(160, 160, 160))
            r += 1
    return np.asarray(canvas)


def figure_labels(report: dict[str, Any]) -> list[str]:
    """The row labels of :func:`evaluate`'s figure rows for ``report``."""
    return ["teacher", "student"] + (["baseline"] if "baseline" in report else []) + ["ceiling"]


def _atomic_json(path: Path, data: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")


def write_outputs(
    report: dict[str, Any], rows: list[list[list[np.ndarray]]], out_dir: str | os.PathLike[str]
) -> tuple[Path, Path]:
    """Write ``report.json`` and ``comparison.png`` into ``out_dir``; returns their paths."""
    out_dir = Path(out_dir)
    report_path = out_dir / "report.json"
    _atomic_json(report_path, report)
    shown = len(rows)
    total = len(report["identity_seeds"])
    notes = [f"yaw {r['input_yaw_deg']:+.0f}" for r in report["per_identity"][:shown]]
    title = (
        f"first {shown} of {total} held-out identities" if shown < total else f"{total} held-out identities"
    ) + "; columns: input, then novel views"
    png = save_png(
        out_dir / "comparison.png", comparison_figure(rows, figure_labels(report), notes=notes, title=title)
    )
    return report_path, png


def summary_table(report: dict[str, Any]) -> str:
    """The printed summary: method | novel PSNR own | vs other identities | specificity | SSIM."""

    def db(v: float | None, sign: bool = False) -> str:
        return "n/a" if v is None else (f"{v:+.2f} dB" if sign else f"{v:.2f} dB")

    def num(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f}"

    head = ("method", "novel PSNR own", "vs other identities", "specificity", "SSIM")
    lines = [head]
    for method in ("student", "baseline", "floor", "ceiling"):
        s = report.get(method)
        if s is None:
            continue
        lines.append(
            (
                method,
                db(s.get("novel_psnr")),
                db(s.get("novel_psnr_other")),
                db(s.get("identity_specificity_db"), sign=True),
                num(s.get("novel_ssim")),
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    out = []
    for j, line in enumerate(lines):
        cells = [line[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(line[1:], widths[1:], strict=True)]
        out.append(" | ".join(cells))
        if j == 0:
            out.append("-+-".join("-" * w for w in widths))
    return "\n".join(out)


def run(
    checkpoint: str | os.PathLike[str],
    *,
    out: str | os.PathLike[str] | None = None,
    settings: EvalSettings | None = None,
    lpips_weights: str | None = None,
    lpips_net: str = "alex",
    teacher_pkl: str | None = None,
    eg3d_source: str | None = None,
    device: str | torch.device = "cpu",
) -> tuple[Path, Path, dict[str, Any]]:
    """Evaluate a checkpoint; returns ``(report.json, comparison.png, report)``."""
    device = torch.device(device)
    ckpt = load_checkpoint(checkpoint, map_location=device)
    cfg: TrainConfig = ckpt["train_config"]
    student = student_from_checkpoint(ckpt, device)
    # The run recorded how its teacher was built; given paths override (e.g. the pickle moved).
    targs = resolve_teacher_args(ckpt, teacher_pkl=teacher_pkl, eg3d_source=eg3d_source)
    teacher = build_teacher(
        ckpt["teacher"],
        triplane_resolution=cfg.triplane_resolution,
        teacher_pkl=targs["teacher_pkl"],
        eg3d_source=targs["eg3d_source"],
        conditioning=targs["conditioning"],  # type: ignore[arg-type]
        device=device,
    )
    lpips: LPIPSLoss | None = None
    lpips_note = None
    try:
        lpips = LPIPSLoss(lpips_net, lpips_weights).to(device)  # type: ignore[arg-type]
    except (LPIPSWeightsNotFound, ImportError) as e:
        if lpips_weights is not None:
            raise
        lpips_note = f"LPIPS not measured: {str(e).splitlines()[0]}"
    # The baseline fits with the run's own perceptual loss when it is weight-free or available.
    try:
        perceptual = build_perceptual(cfg.perceptual, lpips_net=cfg.lpips_net, lpips_weights=lpips_weights)
    except (LPIPSWeightsNotFound, ImportError):
        perceptual = build_perceptual("ssim-grad")
    if perceptual is not None:
        perceptual = perceptual.to(device)
    report, rows = evaluate(
        student, teacher, settings=settings, lpips=lpips, perceptual=perceptual, device=device
    )
    report = {"checkpoint": ckpt["path"], "step": int(ckpt["step"]), "teacher": ckpt["teacher"], **report}
    if lpips_note:
        report["lpips_note"] = lpips_note
    out_dir = (
        Path(out)
        if out is not None
        else Path(ckpt["path"]).parent.parent / f"eval-step-{int(ckpt['step']):06d}"
    )
    report_path, png = write_outputs(report, rows, out_dir)
    return report_path, png, report


#: ``--help``'s description: the docstring's first paragraph and what a run writes (the protocol is in
#: the module docstring).
CLI_DESCRIPTION = (
    "Evaluate a trained encoder on held-out teacher identities: does it follow its input, and how does "
    "it compare with the mean head, the teacher itself and a per-identity optimisation baseline? "
    "Writes report.json and comparison.png into --out (default <run>/eval-step-NNNNNN) and prints a "
    "short table. Every metric is against the teacher at its native plane resolution, on identities "
    "outside the training range."
)
#: The name every command module uses (``lp3d.cli.common.module_command``).
DESCRIPTION = CLI_DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The evaluation options, shared by ``lp3d eval`` and ``python -m lp3d.training.eval``."""
    p.add_argument("checkpoint", help="training checkpoint (.pt) or run directory (its latest checkpoint)")
    default = EvalSettings()
    p.add_argument(
        "--n-identities",
        type=int,
        default=default.n_identities,
        help=f"held-out identities (default {default.n_identities})",
    )
    p.add_argument("--out", default=None, help="output directory (default <run>/eval-step-NNNNNN)")
    p.add_argument(
        "--baseline-steps",
        type=int,
        default=default.baseline_steps,
        help="optimisation steps of the baseline (0: skip)",
    )
    p.add_argument(
        "--lpips-weights", default=None, help="torchvision AlexNet/VGG16 state dict for the LPIPS metric"
    )
    p.add_argument(
        "--lpips-net", choices=("alex", "vgg"), default="alex", help="LPIPS backbone (default alex)"
    )
    p.add_argument(
        "--teacher-pkl",
        default=None,
        help="EG3D generator pickle (EG3D-teacher checkpoints; default: the one the run recorded)",
    )
    p.add_argument(
        "--eg3d-source",
        default=None,
        help="NVlabs/eg3d's eg3d/ folder, to unpickle the generator (default: the one the run recorded)",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser(prog: str = "python -m lp3d.training.eval") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=CLI_DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=run_cli)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.training.eval`` (an alias of ``lp3d eval``); exit status 0, 1 (an error, one
    line) or 2 (usage), as :mod:`lp3d.errors` says."""
    return run_command(build_parser(), argv)


def run_cli(args: argparse.Namespace) -> int:
    """Evaluate with parsed :func:`add_arguments` options; returns the exit status. (:func:`run` is the
    Python API.)"""
    if args.n_identities < 1:
        raise UsageError("--n-identities must be >= 1")
    if args.baseline_steps < 0:
        raise UsageError("--baseline-steps must be >= 0")
    settings = EvalSettings(
        n_identities=args.n_identities, baseline_steps=args.baseline_steps, progress=not args.no_progress
    )
    try:
        report_path, png, report = run(
            args.checkpoint,
            out=args.out,
            settings=settings,
            lpips_weights=args.lpips_weights,
            lpips_net=args.lpips_net,
            teacher_pkl=args.teacher_pkl,
            eg3d_source=args.eg3d_source,
            device=args.device,
        )
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ERROR
    print(summary_table(report))
    s = report["student"]
    print(f"student  : encode {s['encode_ms']:.1f} ms, render {s['render_ms']:.1f} ms per view")
    if "baseline" in report:
        b = report["baseline"]
        print(f"baseline : fit {b['fit_s']:.1f} s ({b['steps']} steps)")
    print(f"wrote {report_path} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
