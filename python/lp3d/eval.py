"""Evaluate a trained encoder on held-out teacher identities, beside a per-identity optimisation baseline.

``python -m lp3d.eval runs/t/checkpoints/step-000200.pt --n-identities 8`` writes ``report.json`` and
``comparison.png`` into ``--out`` (default: ``<run>/eval-step-NNNNNN``).

Protocol (paper §4 measures novel-view quality and depth on real data; here the teacher is the ground
truth, so every quantity is exact):

* identities: teacher seeds ``eval_seed_start + i`` (disjoint from the training range);
* input view: one camera from the training reference distribution (augmented intrinsics, random
  pose), drawn from a generator seeded by the identity seed, so every run sees the same inputs;
* novel views: fixed FFHQ cameras at yaw -30°, 0°, +30° (pitch 0) and pitch +20° (yaw 0);
* image metrics on the final (super-resolved, ``image_size``²) images: PSNR, SSIM and, when its
  backbone weights exist on disk, LPIPS (AlexNet, the usual metric); PSNR also on the raw renders;
* depth (supplement "H3DS"): scale-and-shift-invariant L1 and RMSE on the raw depth maps, with the
  teacher's depth normalised to [0, 1] over pixels the teacher covers (weights_sum > 0.5), the
  student's aligned to it by least squares;
* timing: the encoder's forward (one image) and one view's render (volume render + SR), medians.

Baseline ("like GAN-inversion baselines", e.g. EG3D-PTI): per identity, a triplane fitted to the input
view alone by Adam on L1 (raw and high) plus the run's perceptual loss, through the student's own
decoder and SR (frozen), starting from the mean of 16 training identities' teacher triplanes (the
analogue of GAN inversion's start at the mean latent). It optimises the triplane directly, which is
less constrained than a generator's latent space; it shows what the encoder buys: accuracy against
time.
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
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.camera import FFHQ_FOCAL, look_at_camera
from lp3d.camera_sampling import sample_cameras
from lp3d.images import rgb_to_uint8, save_png, tile
from lp3d.losses import LPIPSLoss, LPIPSWeightsNotFound, build_perceptual, l1, ssim
from lp3d.teachers import Teacher
from lp3d.train import (
    SceneBounds,
    Student,
    TrainConfig,
    build_teacher,
    load_checkpoint,
    render_teacher,
    render_views,
    student_from_checkpoint,
)

__all__ = ["NOVEL_VIEWS", "EvalSettings", "depth_errors", "evaluate", "main", "psnr"]

#: (yaw, pitch) in degrees of the novel views, FFHQ intrinsics and radius.
NOVEL_VIEWS: tuple[tuple[float, float], ...] = ((-30.0, 0.0), (0.0, 0.0), (30.0, 0.0), (0.0, 20.0))


@dataclass(frozen=True)
class EvalSettings:
    """What :func:`evaluate` measures; ``baseline_steps = 0`` skips the baseline."""

    n_identities: int = 8
    novel_views: tuple[tuple[float, float], ...] = NOVEL_VIEWS
    baseline_steps: int = 100
    baseline_lr: float = 0.02
    baseline_mean_of: int = 16
    timing_repeats: int = 3
    #: A progress bar (stderr) over identities and baseline fits.
    progress: bool = False


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


def _mean(values: Sequence[float]) -> float | None:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else None


# --------------------------------------------------------------------------------------------------
# Rendering helpers
# --------------------------------------------------------------------------------------------------


def _views(settings: EvalSettings, device: torch.device) -> Tensor:
    cams = [look_at_camera(yaw_deg=y, pitch_deg=p, focal=FFHQ_FOCAL) for y, p in settings.novel_views]
    return torch.tensor(np.stack(cams), dtype=torch.float32, device=device)


def _render_student(student: Student, planes: Tensor, cams: Tensor) -> dict[str, Tensor]:
    """planes (1, 3, 32, T, T) seen from cams (V, 25): ``high`` (V,3,S,S), ``raw`` (V,3,r,r),
    ``depth`` (V,r,r)."""
    v = cams.shape[0]
    out = render_views(
        planes.expand(v, -1, -1, -1, -1), student.decoder.weights(), cams, student.config, student.scene
    )
    return {"high": student.superres(out["features"]), "raw": out["rgb"], "depth": out["depth"]}


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
    """``(result, median seconds)`` of ``fn()`` over ``repeats`` runs after one warm-up."""
    result = fn()
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


def _mean_triplane(teacher: Teacher, cfg: TrainConfig, n: int, device: torch.device) -> Tensor:
    """Mean of ``n`` training identities' teacher planes at the student's resolution (1, 3, 32, T, T)."""
    lo = cfg.train_seeds[0]
    planes = np.mean([teacher.sample(lo + i).planes.astype(np.float32) for i in range(n)], axis=0)
    t = torch.from_numpy(planes).unsqueeze(0).to(device)
    if t.shape[-1] != cfg.triplane_resolution:
        b, p, c, h, w = t.shape
        t = torch.nn.functional.interpolate(
            t.reshape(1, p * c, h, w), size=(cfg.triplane_resolution,) * 2, mode="bilinear", antialias=True
        ).reshape(1, p, c, cfg.triplane_resolution, cfg.triplane_resolution)
    return t


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
    """The baseline: planes (1, 3, 32, T, T) fitted to one view by Adam, student renderer frozen."""
    planes = init.clone().requires_grad_(True)
    opt = torch.optim.Adam([planes], lr=lr)
    for _ in range(steps):
        out = _render_student(student, planes, camera)
        loss = l1(out["raw"], target_raw) + l1(out["high"], target_high)
        if perceptual is not None:
            loss = loss + perceptual(out["raw"], target_raw) + perceptual(out["high"], target_high)
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
    """Measure ``student`` (and the baseline) on held-out identities.

    Returns:
        ``(report, rows)``: the JSON-ready report and, per identity, image rows (H, W, 3) uint8 for
        the comparison figure: teacher (input, novel views), student, baseline (when run).
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
    decoder = [torch.as_tensor(a, device=device) for a in teacher.decoder()]
    views = _views(settings, device)
    seeds = [cfg.eval_seed_start + i for i in range(settings.n_identities)]
    metrics = {"student": _Metrics(), "baseline": _Metrics()}
    encode_s: list[float] = []
    render_s: list[float] = []
    fit_s: list[float] = []
    rows: list[list[list[np.ndarray]]] = []
    init = (
        _mean_triplane(teacher, cfg, settings.baseline_mean_of, device)
        if settings.baseline_steps > 0
        else None
    )

    def to_u8(x: Tensor) -> np.ndarray:
        return rgb_to_uint8(x.detach().cpu().numpy())

    bar = None
    if settings.progress:
        from tqdm import tqdm

        bar = tqdm(
            total=len(seeds) * (1 + settings.baseline_steps), desc="eval", unit="step", file=sys.stderr
        )
    for seed in seeds:
        if bar is not None:
            bar.set_postfix_str(f"identity seed {seed}")
        tri = teacher.sample(seed)
        planes_t = torch.from_numpy(tri.planes.astype(np.float32)).unsqueeze(0).to(device)
        cam_rng = np.random.Generator(np.random.PCG64(seed))
        cam = torch.from_numpy(sample_cameras(cfg.reference_cameras, 1, cam_rng).labels).float().to(device)
        truth_in = _render_truth(teacher, planes_t, decoder, cam, cfg, student.scene)
        truth_nv = _render_truth(teacher, planes_t, decoder, views, cfg, student.scene)
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
        figure = [
            [to_u8(image[0])] + [to_u8(v) for v in truth_nv["high"]],
            [to_u8(pred_in["high"][0])] + [to_u8(v) for v in pred_nv["high"]],
        ]

        if init is not None:
            t0 = time.perf_counter()
            with torch.enable_grad():
                planes_b = fit_triplane(
                    student,
                    init,
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
            figure.append([to_u8(base_in["high"][0])] + [to_u8(v) for v in base_nv["high"]])
        rows.append(figure)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()

    report: dict[str, Any] = {
        "config": cfg.name,
        "identity_seeds": seeds,
        "novel_views_yaw_pitch_deg": [list(v) for v in settings.novel_views],
        "image_size": cfg.image_size,
        "raw_resolution": cfg.raw_resolution,
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "lpips": None if lpips is None else {"net": lpips.net, "weights": lpips.weights_path},
        "student": {
            **metrics["student"].summary(),
            "encode_ms": 1000 * statistics.median(encode_s),
            "render_ms": 1000 * statistics.median(render_s),
        },
    }
    if init is not None:
        report["baseline"] = {
            "method": "per-identity triplane optimisation (Adam) on the input view, from the mean triplane",
            "steps": settings.baseline_steps,
            "lr": settings.baseline_lr,
            **metrics["baseline"].summary(),
            "fit_s": statistics.median(fit_s),
            "render_ms": 1000 * statistics.median(render_s),
        }
    return report, rows


def comparison_figure(rows: list[list[list[np.ndarray]]], labels: Sequence[str]) -> np.ndarray:
    """One image: per identity, one row per method (``labels``), with the label at the left."""
    from PIL import Image, ImageDraw

    flat = [img for identity in rows for row in identity for img in row]
    columns = len(rows[0][0])
    grid = tile(flat, columns)
    margin = 72
    canvas = Image.new("RGB", (grid.shape[1] + margin, grid.shape[0]), (24, 24, 24))
    canvas.paste(Image.fromarray(grid), (margin, 0))
    draw = ImageDraw.Draw(canvas)
    h = rows[0][0][0].shape[0]
    r = 0
    for identity in rows:
        for i, _ in enumerate(identity):
            draw.text((4, 2 + r * (h + 2) + h // 2 - 6), labels[i], fill=(230, 230, 230))
            r += 1
    return np.asarray(canvas)


def _atomic_json(path: Path, data: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")


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
    teacher = build_teacher(
        ckpt["teacher"], triplane_resolution=cfg.triplane_resolution, teacher_pkl=teacher_pkl
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
    report_path = out_dir / "report.json"
    _atomic_json(report_path, report)
    labels = ["teacher", "student", "baseline"]
    png = save_png(out_dir / "comparison.png", comparison_figure(rows, labels))
    return report_path, png, report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lp3d.eval", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="training checkpoint (.pt) or run directory (its latest checkpoint)")
    p.add_argument("--n-identities", type=int, default=8, help="held-out identities (default 8)")
    p.add_argument("--out", default=None, help="output directory (default <run>/eval-step-NNNNNN)")
    p.add_argument(
        "--baseline-steps", type=int, default=100, help="optimisation steps of the baseline (0: skip)"
    )
    p.add_argument(
        "--lpips-weights", default=None, help="torchvision AlexNet/VGG16 state dict for the LPIPS metric"
    )
    p.add_argument(
        "--lpips-net", choices=("alex", "vgg"), default="alex", help="LPIPS backbone (default alex)"
    )
    p.add_argument("--teacher-pkl", default=None, help="EG3D generator pickle (EG3D-teacher checkpoints)")
    p.add_argument(
        "--eg3d-source", default=None, help="NVlabs/eg3d's eg3d/ folder, to unpickle the generator"
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if args.n_identities < 1:
        p.error("--n-identities must be >= 1")
    if args.baseline_steps < 0:
        p.error("--baseline-steps must be >= 0")
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
        return 2
    s = report["student"]
    print(
        f"student  : novel PSNR {s['novel_psnr']:.2f} dB, input PSNR {s['input_psnr']:.2f} dB, "
        f"encode {s['encode_ms']:.1f} ms, render {s['render_ms']:.1f} ms"
    )
    if "baseline" in report:
        b = report["baseline"]
        print(
            f"baseline : novel PSNR {b['novel_psnr']:.2f} dB, input PSNR {b['input_psnr']:.2f} dB, "
            f"fit {b['fit_s']:.1f} s ({b['steps']} steps)"
        )
    print(f"wrote {report_path} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
