"""How ``lp3d encode --refine`` should fit: a sweep of its learning rate, prior weight and steps.

    python bench/refine_sweep.py CHECKPOINT.pt --n-identities 4     # about 4 min on a 2-core CPU

For held-out identities *outside* ``lp3d eval``'s (teacher seeds ``eval_seed_start + 100 ..``, so
the defaults are not tuned on the identities that score them), inputs rendered as ``lp3d eval``
renders them, the student's planes are refined with each setting (``--pose`` names the camera they
are fitted at; finding it is counted in the time). Printed: per setting, the mean input-view and
novel-view PSNR (128², against the
teacher at its native planes) and their gains over the encoder alone, and seconds per image; a
Markdown table for ``bench/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import statistics
import sys
import time

import numpy as np
import torch

from lp3d.evaluation.metrics import psnr
from lp3d.evaluation.protocol import (
    EvalSettings,
    input_camera,
    input_yaws,
    novel_view_cameras,
    reference_teachers,
    render_student,
    render_truth,
)
from lp3d.lift.pose import camera_at, estimate_pose, fit_pose
from lp3d.lift.refine import RefineSettings, refine_planes
from lp3d.render.camera import camera_summary
from lp3d.training.checkpoint import load_checkpoint, student_from_checkpoint
from lp3d.training.teacher_factory import build_teacher


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="training checkpoint (.pt) of the student")
    p.add_argument("--n-identities", type=int, default=4)
    p.add_argument("--steps", default="40", help="comma-separated step counts (default 40)")
    p.add_argument("--lr", default="0.005,0.01,0.02", help="comma-separated learning rates")
    p.add_argument("--prior", default="0,0.05,0.2,1", help="comma-separated prior weights")
    p.add_argument(
        "--pose",
        choices=("found", "grid", "true"),
        default="found",
        help="the camera the planes are fitted at: 'found' as lp3d encode --refine finds a photo's "
        "(grid search, then fitted), 'grid' the grid search's alone, 'true' the input view's true camera "
        "(as lp3d eval's baseline has); default found",
    )
    args = p.parse_args(argv)

    ckpt = load_checkpoint(args.checkpoint)
    student = student_from_checkpoint(ckpt)
    cfg = student.config
    teacher = build_teacher(ckpt["teacher"], triplane_resolution=cfg.triplane_resolution)
    truth_teacher, _ = reference_teachers(teacher, cfg)
    truth_dec = [torch.as_tensor(a) for a in truth_teacher.decoder()]
    decoder = tuple(w.detach().float() for w in student.decoder.weights())
    views = novel_view_cameras(EvalSettings(), torch.device("cpu"))
    seeds = [cfg.eval_seed_start + 100 + i for i in range(args.n_identities)]
    yaws = input_yaws(args.n_identities)

    items, errors = [], []
    for seed, yaw in zip(seeds, yaws, strict=True):
        planes_t = torch.from_numpy(truth_teacher.sample(seed).planes.astype(np.float32)).unsqueeze(0)
        cam = torch.from_numpy(input_camera(cfg, seed, float(yaw))[0]).float().unsqueeze(0)
        truth_in = render_truth(truth_teacher, planes_t, truth_dec, cam, cfg, student.scene)
        truth_nv = render_truth(truth_teacher, planes_t, truth_dec, views, cfg, student.scene)
        with torch.no_grad():
            planes = student.encode(truth_in["high"])[0]
            base_in = float(psnr(render_student(student, planes[None], cam)["high"], truth_in["high"]).mean())
            base_nv = float(
                psnr(render_student(student, planes[None], views)["high"], truth_nv["high"]).mean()
            )
        image = truth_in["high"][0]
        t0 = time.perf_counter()
        if args.pose == "true":
            camera = cam[0]
        else:
            camera = camera_at(*estimate_pose(planes, decoder, student.scene, image, RefineSettings()))
            if args.pose == "found":
                camera = fit_pose(planes, decoder, student.scene, image, camera, RefineSettings())
        pose_s = time.perf_counter() - t0
        found, true = camera_summary(camera.double().numpy()), camera_summary(cam[0].double().numpy())
        errors.append((abs(found["yaw_deg"] - true["yaw_deg"]), abs(found["pitch_deg"] - true["pitch_deg"])))
        items.append((seed, camera, cam, truth_in, truth_nv, planes, pose_s, base_in, base_nv))
        print(
            f"identity {seed}: true yaw {true['yaw_deg']:+.1f}, pitch {true['pitch_deg']:+.1f}; "
            f"{args.pose} camera yaw {found['yaw_deg']:+.1f}, pitch {found['pitch_deg']:+.1f} "
            f"({pose_s:.1f} s)",
            file=sys.stderr,
        )

    rows = []
    grid = list(
        itertools.product([int(s) for s in _floats(args.steps)], _floats(args.lr), _floats(args.prior))
    )
    for steps, lr, prior in grid:
        settings = dataclasses.replace(RefineSettings(), steps=steps, lr=lr, prior_weight=prior)
        d_in, d_nv, secs = [], [], []
        for _, camera, cam, truth_in, truth_nv, planes, pose_s, base_in, base_nv in items:
            t0 = time.perf_counter()
            refined, _ = refine_planes(planes, decoder, student.scene, truth_in["high"][0], camera, settings)
            secs.append(pose_s + time.perf_counter() - t0)
            with torch.no_grad():
                r_in = float(
                    psnr(render_student(student, refined[None], cam)["high"], truth_in["high"]).mean()
                )
                r_nv = float(
                    psnr(render_student(student, refined[None], views)["high"], truth_nv["high"]).mean()
                )
            d_in.append(r_in - base_in)
            d_nv.append(r_nv - base_nv)
        rows.append(
            (steps, lr, prior, statistics.fmean(d_in), statistics.fmean(d_nv), statistics.median(secs))
        )
        print(
            f"steps {steps} lr {lr} prior {prior}: input {rows[-1][3]:+.2f} dB, novel {rows[-1][4]:+.2f} dB, "
            f"{rows[-1][5]:.1f} s",
            file=sys.stderr,
        )

    base_in = statistics.fmean(it[7] for it in items)
    base_nv = statistics.fmean(it[8] for it in items)
    print(
        f"\nencoder alone: input view {base_in:.2f} dB, novel views {base_nv:.2f} dB "
        f"({len(items)} identities, seeds {seeds[0]}..{seeds[-1]}, torch threads {torch.get_num_threads()}; "
        f"fitted at the {args.pose} camera; its mean error: yaw {statistics.fmean(e[0] for e in errors):.1f}"
        f"°, pitch {statistics.fmean(e[1] for e in errors):.1f}°)\n"
    )
    print("| steps | lr | prior weight | input view gain | novel view gain | s / image |")
    print("|---:|---:|---:|---:|---:|---:|")
    for steps, lr, prior, gi, gn, s in rows:
        print(f"| {steps} | {lr:g} | {prior:g} | {gi:+.2f} dB | {gn:+.2f} dB | {s:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
