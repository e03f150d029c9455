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

With ``flip_average``, the method ``flip_averaged`` is the student's flip-averaged encoding
(``lp3d encode --flip-average``, :mod:`lp3d.lift.flip_average`), scored as the student is.

``report.json``: run facts, ``identity_seeds``, ``input_yaw_deg``, ``per_identity`` (per seed: input
yaw and pitch, own/other PSNR and SSIM, specificity, floor, ceiling and, when run, baseline PSNR), the
averages per method under ``student``, ``baseline``, ``floor`` and ``ceiling``, and the student's
``identity_specificity_db`` at the top level. ``comparison.png`` shows, for the first
``figure_identities`` (default 8) identities, rows teacher (input, then the novel views), student,
baseline (when run) and ceiling (novel views only).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from lp3d.evaluation.identities import (
    EvalRun,
    build_report,
    fit_baseline,
    mean_triplane,
    refine_identity,
    to_uint8,
)
from lp3d.evaluation.metrics import (
    depth_errors,
    psnr,
)
from lp3d.evaluation.package_student import is_package, package_student
from lp3d.evaluation.protocol import (
    INPUT_YAW_RANGE_DEG,
    NOVEL_VIEWS,
    EvalSettings,
    input_camera,
    input_yaws,
    novel_view_cameras,
    planes_tensor,
    reference_teachers,
    render_student,
    render_truth,
    resample_planes,
    timed,
)
from lp3d.evaluation.report import (
    comparison_figure,
    figure_labels,
    summary_table,
    write_outputs,
)
from lp3d.lift.flip_average import flip_averaged
from lp3d.lift.refine import RefineSettings
from lp3d.teachers import Teacher
from lp3d.training.checkpoint import load_checkpoint, student_from_checkpoint
from lp3d.training.config import TrainConfig
from lp3d.training.losses import LPIPSLoss, LPIPSWeightsNotFound, build_perceptual
from lp3d.training.student import Student
from lp3d.training.teacher_factory import build_teacher, resolve_teacher_args

__all__ = [
    "INPUT_YAW_RANGE_DEG",
    "NOVEL_VIEWS",
    "EvalSettings",
    "comparison_figure",
    "depth_errors",
    "evaluate",
    "evaluate_checkpoint",
    "figure_labels",
    "input_camera",
    "input_yaws",
    "psnr",
    "reference_teachers",
    "summary_table",
    "write_outputs",
]


# --------------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------------


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
    truth_teacher, ceiling_teacher = reference_teachers(teacher, cfg)
    run_dec = [torch.as_tensor(a, device=device) for a in teacher.decoder()]
    views = novel_view_cameras(settings, device)
    n = settings.n_identities
    seeds = [cfg.eval_seed_start + i for i in range(n)]
    yaws = [float(y) for y in input_yaws(n, settings.input_yaw_range_deg)]
    # The floor: the mean head, one render for every identity (and the baseline's start).
    mean_planes = mean_triplane(teacher, cfg, settings.baseline_mean_of, device)
    floor_nv = render_truth(teacher, mean_planes, run_dec, views, cfg, student.scene)
    run = EvalRun(
        student=student,
        settings=settings,
        lpips=lpips,
        perceptual=perceptual,
        device=device,
        truth_teacher=truth_teacher,
        ceiling_teacher=ceiling_teacher,
        truth_dec=[torch.as_tensor(a, device=device) for a in truth_teacher.decoder()],
        run_dec=run_dec,
        views=views,
        mean_planes=mean_planes,
        floor_nv=floor_nv,
    )
    run.high["floor"].append(floor_nv["high"])
    run.raw["floor"].append(floor_nv["raw"])
    if settings.progress:
        from tqdm import tqdm

        run.bar = tqdm(
            total=n * (1 + _refine_steps(settings.refine) + settings.baseline_steps),
            desc="eval",
            unit="step",
            file=sys.stderr,
        )
    for k, seed in enumerate(seeds):
        _evaluate_identity(run, teacher, seed, yaws[k], show=k < settings.figure_identities)
    if run.bar is not None:
        run.bar.close()
    return build_report(run, seeds, yaws), run.rows


def _refine_steps(refine: RefineSettings) -> int:
    """Progress steps of one identity's refinements: at the true camera, then as a photo (the camera's
    steps, then the planes')."""
    return 0 if refine.steps == 0 else refine.steps + refine.total_steps()


def _evaluate_identity(run: EvalRun, teacher: Teacher, seed: int, yaw: float, *, show: bool) -> None:
    """One held-out identity: its truth renders, the student's, the floor's, the ceiling's and (when
    run) the baseline's; ``show`` adds its rows to the comparison figure."""
    student, settings, device, views = run.student, run.settings, run.device, run.views
    cfg, scene = student.config, student.scene
    if run.bar is not None:
        run.bar.set_postfix_str(f"identity seed {seed}")
    planes_t = planes_tensor(run.truth_teacher.sample(seed), device)
    run.truth_resolution = int(planes_t.shape[-1])
    label, pitch = input_camera(cfg, seed, yaw)
    run.pitches.append(pitch)
    cam = torch.from_numpy(label).float().unsqueeze(0).to(device)
    truth_in = render_truth(run.truth_teacher, planes_t, run.truth_dec, cam, cfg, scene)
    truth_nv = render_truth(run.truth_teacher, planes_t, run.truth_dec, views, cfg, scene)
    run.truths.append(truth_nv)
    image = truth_in["high"]

    with torch.no_grad():
        planes_s, t_enc = timed(lambda image=image: student.encode(image), device, settings.timing_repeats)
        pred_in, t_ren = timed(
            lambda p=planes_s, c=cam: render_student(student, p, c), device, settings.timing_repeats
        )
        pred_nv = render_student(student, planes_s, views)
    run.encode_s.append(t_enc)
    run.render_s.append(t_ren)
    run.metrics["student"].add("input", pred_in, truth_in, run.lpips)
    run.add("student", pred_nv, truth_nv)
    run.metrics["floor"].add("novel", run.floor_nv, truth_nv, run.lpips)
    if settings.flip_average:
        with torch.no_grad():
            planes_f, t_flip = timed(
                lambda image=image: flip_averaged(student.encode, image), device, settings.timing_repeats
            )
            pred_f = render_student(student, planes_f, cam)
            run.metrics["flip_averaged"].add("input", pred_f, truth_in, run.lpips)
            run.add("flip_averaged", render_student(student, planes_f, views), truth_nv)
        run.flip_encode_s.append(t_flip)

    # The ceiling: the teacher's own head at the student's plane resolution.
    if run.ceiling_teacher is not None:
        planes_c = planes_tensor(run.ceiling_teacher.sample(seed), device)
    else:
        planes_c = resample_planes(planes_t, cfg.triplane_resolution)
    ceil_nv = render_truth(teacher, planes_c, run.run_dec, views, cfg, scene)
    run.add("ceiling", ceil_nv, truth_nv)

    figure = []
    if show:
        figure = [
            [to_uint8(image[0])] + [to_uint8(v) for v in truth_nv["high"]],
            [to_uint8(pred_in["high"][0])] + [to_uint8(v) for v in pred_nv["high"]],
        ]
    if settings.refine.steps > 0:
        ref_in, ref_nv = refine_identity(run, planes_s, image, cam, truth_in, truth_nv)
        if show:
            figure.append([to_uint8(ref_in["high"][0])] + [to_uint8(v) for v in ref_nv["high"]])
    if settings.baseline_steps > 0:
        base_in, base_nv = fit_baseline(run, cam, truth_in, truth_nv)
        if show:
            figure.append([to_uint8(base_in["high"][0])] + [to_uint8(v) for v in base_nv["high"]])
    if show:
        blank = np.full_like(figure[0][0], 24)
        figure.append([blank] + [to_uint8(v) for v in ceil_nv["high"]])
        run.rows.append(figure)
    if run.bar is not None:
        run.bar.update(1)


# --------------------------------------------------------------------------------------------------
# The command line
# --------------------------------------------------------------------------------------------------


def evaluate_checkpoint(
    checkpoint: str | os.PathLike[str],
    *,
    out: str | os.PathLike[str] | None = None,
    settings: EvalSettings | None = None,
    lpips_weights: str | None = None,
    lpips_net: str = "alex",
    teacher_pkl: str | None = None,
    eg3d_source: str | None = None,
    device: str | torch.device = "cpu",
    teacher_name: str | None = None,
) -> tuple[Path, Path, dict[str, Any]]:
    """Evaluate a checkpoint; returns ``(report.json, comparison.png, report)``. ``teacher_name``
    overrides the teacher the run recorded (runs made before procedural teacher v2 recorded
    ``procedural`` for what is now ``procedural-v1``)."""
    device = torch.device(device)
    if is_package(checkpoint):  # MODEL.onnx or MODEL.pt: the package's own student, its sidecar's config
        student, ckpt = package_student(checkpoint, device)
    else:
        ckpt = load_checkpoint(checkpoint, map_location=device)
        student = student_from_checkpoint(ckpt, device)
    cfg: TrainConfig = ckpt["train_config"]
    # The run recorded how its teacher was built; given paths override (e.g. the pickle moved).
    targs = resolve_teacher_args(ckpt, teacher_pkl=teacher_pkl, eg3d_source=eg3d_source)
    teacher_name = teacher_name or ckpt["teacher"]
    teacher = build_teacher(
        teacher_name,
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
    step = None if ckpt["step"] is None else int(ckpt["step"])
    report = {"checkpoint": ckpt["path"], "step": step, "teacher": teacher_name, **report}
    if lpips_note:
        report["lpips_note"] = lpips_note
    if out is not None:
        out_dir = Path(out)
    elif step is None:  # a package (maybe installed, not writable): in the working folder, named for it
        out_dir = Path(f"{Path(ckpt['path']).stem}-eval")
    else:
        out_dir = Path(ckpt["path"]).parent.parent / f"eval-step-{step:06d}"
    report_path, png = write_outputs(report, rows, out_dir)
    return report_path, png, report
