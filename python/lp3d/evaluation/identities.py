"""One evaluation's state and the report made from it: :class:`EvalRun` (what each held-out identity's step
reads and adds), the optimisation baseline (:func:`fit_triplane`) and the report (:func:`build_report`).
:mod:`lp3d.evaluation.evaluate` runs the identities.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.evaluation.metrics import (
    CrossScores,
    ViewScores,
)
from lp3d.evaluation.protocol import (
    EvalSettings,
    render_student,
    resample_planes,
    sync_device,
)
from lp3d.images import rgb_to_uint8
from lp3d.lift.pose import find_camera
from lp3d.lift.refine import refine_planes
from lp3d.render.camera import camera_summary
from lp3d.teachers import Teacher
from lp3d.training.config import TrainConfig
from lp3d.training.losses import LPIPSLoss, l1
from lp3d.training.student import Student, render_views


def mean_triplane(teacher: Teacher, cfg: TrainConfig, n: int, device: torch.device) -> Tensor:
    """Mean of ``n`` training identities' teacher planes at the student's resolution (1, 3, 32, T, T)."""
    lo = cfg.train_seeds[0]
    planes = np.mean([teacher.sample(lo + i).planes.astype(np.float32) for i in range(n)], axis=0)
    t = torch.from_numpy(planes).unsqueeze(0).to(device)
    return resample_planes(t, cfg.triplane_resolution)


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
            out = render_student(student, planes, camera)
            pairs = [(out["raw"], target_raw), (out["high"], target_high)]
        loss = sum(l1(a, b) + (perceptual(a, b) if perceptual is not None else 0.0) for a, b in pairs)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if on_step is not None:
            on_step()
    return planes.detach()


METHODS = ("student", "flip_averaged", "refined", "refined_photo", "baseline", "floor", "ceiling")


@dataclass
class EvalRun:
    """One evaluation: what every identity's step reads (``student`` ... ``floor_nv``) and what it adds
    (the remaining fields, per method and identity)."""

    student: Student
    settings: EvalSettings
    lpips: LPIPSLoss | None
    perceptual: nn.Module | None
    device: torch.device
    truth_teacher: Teacher
    ceiling_teacher: Teacher | None
    truth_dec: list[Tensor]
    run_dec: list[Tensor]
    views: Tensor
    mean_planes: Tensor
    floor_nv: dict[str, Tensor]
    bar: Any = None
    metrics: dict[str, ViewScores] = field(default_factory=lambda: {m: ViewScores() for m in METHODS})
    # Per method and identity: the novel views' final and raw renders (for the cross-identity scores).
    high: dict[str, list[Tensor]] = field(default_factory=lambda: {m: [] for m in METHODS})
    raw: dict[str, list[Tensor]] = field(default_factory=lambda: {m: [] for m in METHODS})
    truths: list[dict[str, Tensor]] = field(default_factory=list)
    pitches: list[float] = field(default_factory=list)
    encode_s: list[float] = field(default_factory=list)
    flip_encode_s: list[float] = field(default_factory=list)
    render_s: list[float] = field(default_factory=list)
    fit_s: list[float] = field(default_factory=list)
    refine_s: list[float] = field(default_factory=list)
    photo_refine_s: list[float] = field(default_factory=list)
    #: Per identity: (yaw, pitch) of the camera lp3d encode --refine finds, and of the true one.
    found_poses: list[tuple[float, float]] = field(default_factory=list)
    true_poses: list[tuple[float, float]] = field(default_factory=list)
    rows: list[list[list[np.ndarray]]] = field(default_factory=list)
    truth_resolution: int | None = None

    def add(self, method: str, pred_nv: dict[str, Tensor], truth_nv: dict[str, Tensor]) -> None:
        """A method's novel views of one identity: scored, and kept for the cross-identity scores."""
        self.metrics[method].add("novel", pred_nv, truth_nv, self.lpips)
        self.high[method].append(pred_nv["high"])
        self.raw[method].append(pred_nv["raw"])


def to_uint8(x: Tensor) -> np.ndarray:
    return rgb_to_uint8(x.detach().cpu().numpy())


def fit_baseline(
    run: EvalRun, cam: Tensor, truth_in: dict[str, Tensor], truth_nv: dict[str, Tensor]
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """The optimisation baseline for one identity: fitted, timed, scored; returns its renders."""
    student, settings = run.student, run.settings
    t0 = time.perf_counter()
    with torch.enable_grad():
        planes_b = fit_triplane(
            student,
            run.mean_planes,
            cam,
            truth_in["high"],
            truth_in["raw"],
            steps=settings.baseline_steps,
            lr=settings.baseline_lr,
            perceptual=run.perceptual,
            on_step=None if run.bar is None else run.bar.update,
        )
    sync_device(run.device)
    run.fit_s.append(time.perf_counter() - t0)
    with torch.no_grad():
        base_in = render_student(student, planes_b, cam)
        base_nv = render_student(student, planes_b, run.views)
    run.metrics["baseline"].add("input", base_in, truth_in, run.lpips)
    run.add("baseline", base_nv, truth_nv)
    return base_in, base_nv


def refine_identity(
    run: EvalRun,
    planes_s: Tensor,
    image: Tensor,
    cam: Tensor,
    truth_in: dict[str, Tensor],
    truth_nv: dict[str, Tensor],
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """``lp3d encode --refine`` for one identity, twice: ``refined``, fitted at the true input camera as
    the baseline is, and ``refined_photo``, fitted as a user's photo is, at the camera it finds from
    the image (timed with the finding). Both scored; returns ``refined``'s renders."""
    student, settings = run.student, run.settings
    planes, image0 = planes_s[0].detach().cpu(), image[0].detach().cpu()
    decoder = tuple(w.detach().cpu().float() for w in student.decoder.weights())
    tick = None if run.bar is None else run.bar.update
    scores = {}
    for method in ("refined", "refined_photo"):
        t0 = time.perf_counter()
        with torch.enable_grad():
            if method == "refined":
                camera = cam[0].detach().cpu()
            else:
                camera = find_camera(planes, decoder, student.scene, image0, settings.refine, on_step=tick)
            refined, camera = refine_planes(
                planes, decoder, student.scene, image0, camera, settings.refine, on_step=tick
            )
        (run.refine_s if method == "refined" else run.photo_refine_s).append(time.perf_counter() - t0)
        if method == "refined_photo":
            found, true = (
                camera_summary(camera.double().numpy()),
                camera_summary(cam[0].double().cpu().numpy()),
            )
            run.found_poses.append((found["yaw_deg"], found["pitch_deg"]))
            run.true_poses.append((true["yaw_deg"], true["pitch_deg"]))
        planes_r = refined[None].to(planes_s.device)
        with torch.no_grad():  # scored at the true input camera, as every method is
            scores[method] = (
                render_student(student, planes_r, cam),
                render_student(student, planes_r, run.views),
            )
        run.metrics[method].add("input", scores[method][0], truth_in, run.lpips)
        run.add(method, scores[method][1], truth_nv)
    return scores["refined"]


def _per_identity(
    run: EvalRun, cross: dict[str, CrossScores], seeds: list[int], yaws: list[float]
) -> list[dict[str, Any]]:
    """``report.json``'s per-identity rows."""
    per_method = {m: c.per_identity() for m, c in cross.items()}
    per_identity: list[dict[str, Any]] = []
    for k, seed in enumerate(seeds):
        s = per_method["student"][k]
        row: dict[str, Any] = {
            "seed": seed,
            "input_yaw_deg": yaws[k],
            "input_pitch_deg": run.pitches[k],
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
        row["input_psnr"] = run.metrics["student"].values["input_psnr"][k]
        if "flip_averaged" in per_method:
            f = per_method["flip_averaged"][k]
            row["flip_averaged_input_psnr"] = run.metrics["flip_averaged"].values["input_psnr"][k]
            row["flip_averaged_novel_psnr"] = f["novel_psnr"]
            row["flip_averaged_identity_specificity_db"] = f["identity_specificity_db"]
        if "refined" in per_method:
            r = per_method["refined"][k]
            row["refined_input_psnr"] = run.metrics["refined"].values["input_psnr"][k]
            row["refined_novel_psnr"] = r["novel_psnr"]
            row["refined_identity_specificity_db"] = r["identity_specificity_db"]
            p = per_method["refined_photo"][k]
            row["photo_refined_input_psnr"] = run.metrics["refined_photo"].values["input_psnr"][k]
            row["photo_refined_novel_psnr"] = p["novel_psnr"]
            row["found_camera_yaw_pitch_deg"] = list(run.found_poses[k])
            row["true_camera_yaw_pitch_deg"] = list(run.true_poses[k])
        if "baseline" in per_method:
            b = per_method["baseline"][k]
            row["baseline_novel_psnr"] = b["novel_psnr"]
            row["baseline_identity_specificity_db"] = b["identity_specificity_db"]
        per_identity.append(row)
    return per_identity


# Long because: one dict literal, the report's layout (module docstring), read top to bottom.
def build_report(run: EvalRun, seeds: list[int], yaws: list[float]) -> dict[str, Any]:
    """The JSON-ready report of a finished run (its layout is in the module docstring)."""
    settings, metrics = run.settings, run.metrics
    cfg, t_res = run.student.config, run.student.config.triplane_resolution
    ceiling_teacher, device = run.ceiling_teacher, run.device
    cross = {m: CrossScores.of(run.high[m], run.raw[m], run.truths) for m in METHODS if run.high[m]}
    student_summary = {**metrics["student"].summary(), **cross["student"].summary()}
    report: dict[str, Any] = {
        "config": cfg.name,
        "identity_seeds": seeds,
        "input_yaw_deg": yaws,
        "input_pitch_deg": run.pitches,
        "novel_views_yaw_pitch_deg": [list(v) for v in settings.novel_views],
        "image_size": cfg.image_size,
        "raw_resolution": cfg.raw_resolution,
        "triplane_resolution": t_res,
        "truth": {
            "teacher": type(run.truth_teacher).__name__,
            "plane_resolution": run.truth_resolution,
            "note": "every metric is against this teacher at its native plane resolution; the encoder's "
            "input is rendered from it too",
        },
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "lpips": None if run.lpips is None else {"net": run.lpips.net, "weights": run.lpips.weights_path},
        "identity_specificity_db": student_summary["identity_specificity_db"],
        "student": {
            **student_summary,
            "encode_ms": 1000 * statistics.median(run.encode_s),
            "render_ms": 1000 * statistics.median(run.render_s),
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
        "per_identity": _per_identity(run, cross, seeds, yaws),
    }
    if settings.flip_average:
        report["flip_averaged"] = {
            "method": "lp3d encode --flip-average: the mean of the student's planes of the input and the "
            "mirror of its planes of the input flipped left to right (lp3d.lift.flip_average)",
            **metrics["flip_averaged"].summary(),
            **cross["flip_averaged"].summary(),
            "encode_ms": 1000 * statistics.median(run.flip_encode_s),
        }
    if settings.refine.steps > 0:
        report["refined"] = {
            "method": "lp3d encode --refine: the student's planes fitted to the input view (Adam, L1 on "
            "raw RGB plus a prior that holds them near the student's), at the true input camera as the "
            "baseline is",
            "settings": run.settings.refine.to_dict(),
            **metrics["refined"].summary(),
            **cross["refined"].summary(),
            "refine_s": statistics.median(run.refine_s),
        }
        yaw_err = [abs(f[0] - t[0]) for f, t in zip(run.found_poses, run.true_poses, strict=True)]
        pitch_err = [abs(f[1] - t[1]) for f, t in zip(run.found_poses, run.true_poses, strict=True)]
        report["refined_photo"] = {
            "method": "lp3d encode --refine as a photo gets it: the same fit at the camera "
            "lp3d.lift.pose.find_camera finds from the image (grid search, then fitted), scored at the "
            "true camera; the time includes finding the camera",
            **metrics["refined_photo"].summary(),
            **cross["refined_photo"].summary(),
            "refine_s": statistics.median(run.photo_refine_s),
            "camera_yaw_error_deg": statistics.fmean(yaw_err),
            "camera_pitch_error_deg": statistics.fmean(pitch_err),
        }
    if settings.baseline_steps > 0:
        report["baseline"] = {
            "method": "per-identity triplane optimisation (Adam) on the input view, from the mean triplane",
            "steps": settings.baseline_steps,
            "lr": settings.baseline_lr,
            **metrics["baseline"].summary(),
            **cross["baseline"].summary(),
            "fit_s": statistics.median(run.fit_s),
            "render_ms": 1000 * statistics.median(run.render_s),
        }
    return report
