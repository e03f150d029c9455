"""``lp3d eval``: evaluate a trained encoder on held-out teacher
identities with :func:`lp3d.evaluation.evaluate_checkpoint`.

The library needs torch (the ``train`` extra), so it is imported only when this subcommand is parsed
or run."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from lp3d.errors import UsageError, UserError, int_in, run_command

HELP = "evaluate a trained encoder on held-out identities (needs torch)"
#: This subcommand's options import torch: the top-level parser adds them only when it is named.
LAZY = True
DESCRIPTION = (
    "Evaluate a trained encoder on held-out teacher identities: does it follow its input, and how does "
    "it compare with the mean head, the teacher itself and a per-identity optimisation baseline? "
    "Writes report.json and comparison.png into --out (default <run>/eval-step-NNNNNN; MODEL-eval for a "
    "package) and prints a short table. Every metric is against the teacher at its native plane "
    "resolution, on identities outside the training range."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The evaluation options of ``lp3d eval``."""
    from lp3d.evaluation import EvalSettings
    from lp3d.lift.refine_settings import MAX_STEPS as REFINE_MAX_STEPS
    from lp3d.training.teacher_factory import TEACHERS

    p.add_argument(
        "checkpoint",
        help="training checkpoint (.pt), run directory (its latest checkpoint), or a model package's "
        "MODEL.onnx (its MODEL.json and torch weights MODEL.pt beside it: the shipped model, an export)",
    )
    default = EvalSettings()
    p.add_argument(
        "--n-identities",
        type=int,
        default=default.n_identities,
        help=f"held-out identities (default {default.n_identities})",
    )
    p.add_argument(
        "--out",
        default=None,
        help="output directory (default <run>/eval-step-NNNNNN; ./MODEL-eval for a package)",
    )
    p.add_argument(
        "--baseline-steps",
        type=int,
        default=default.baseline_steps,
        help="optimisation steps of the baseline (0: skip)",
    )
    p.add_argument(
        "--refine",
        type=int_in(0, REFINE_MAX_STEPS),
        default=0,
        metavar="N",
        help="also score lp3d encode --refine N (N steps of fitting the student's planes to the input "
        "view, at the true camera and at the camera found from the image; default 0: skip)",
    )
    p.add_argument(
        "--flip-average",
        action="store_true",
        help="also score lp3d encode --flip-average (the planes of the input and of its mirror image, "
        "averaged) as the row flip_averaged",
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
    p.add_argument(
        "--teacher",
        choices=TEACHERS,
        default=None,
        help="the run's teacher (default: the one it recorded; runs made before procedural teacher v2 "
        "recorded 'procedural' for procedural-v1)",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Evaluate with parsed :func:`add_arguments` options; prints the table; returns the exit status."""
    from lp3d.evaluation import EvalSettings, evaluate_checkpoint, summary_table
    from lp3d.lift.refine_settings import RefineSettings

    if args.n_identities < 1:
        raise UsageError("--n-identities must be >= 1")
    if args.baseline_steps < 0:
        raise UsageError("--baseline-steps must be >= 0")
    settings = EvalSettings(
        n_identities=args.n_identities,
        baseline_steps=args.baseline_steps,
        refine=RefineSettings(steps=args.refine),
        flip_average=args.flip_average,
        progress=not args.no_progress,
    )
    try:
        report_path, png, report = evaluate_checkpoint(
            args.checkpoint,
            out=args.out,
            settings=settings,
            lpips_weights=args.lpips_weights,
            lpips_net=args.lpips_net,
            teacher_pkl=args.teacher_pkl,
            eg3d_source=args.eg3d_source,
            device=args.device,
            teacher_name=args.teacher,
        )
    except (
        RuntimeError
    ) as e:  # a device or model failure; ValueError and OSError reach run_command as they are
        raise UserError(str(e)) from None
    print(summary_table(report))
    s = report["student"]
    print(f"student  : encode {s['encode_ms']:.1f} ms, render {s['render_ms']:.1f} ms per view")
    if "flip_averaged" in report:
        print(f"flip_averaged: encode {report['flip_averaged']['encode_ms']:.1f} ms")
    if "refined" in report:
        r, p = report["refined"], report["refined_photo"]
        print(f"refined  : fit {r['refine_s']:.1f} s ({r['settings']['steps']} steps)")
        print(
            f"refined_photo: camera found and fitted in {p['refine_s']:.1f} s; camera error yaw "
            f"{p['camera_yaw_error_deg']:.1f}°, pitch {p['camera_pitch_error_deg']:.1f}°"
        )
    if "baseline" in report:
        b = report["baseline"]
        print(f"baseline : fit {b['fit_s']:.1f} s ({b['steps']} steps)")
    print(f"wrote {report_path} and {png}")
    return 0


def build_parser(prog: str = "lp3d eval") -> argparse.ArgumentParser:
    """This command's parser on its own (as ``lp3d-view``'s is)."""
    from lp3d.cli import standalone_parser

    return standalone_parser(sys.modules[__name__], prog)


def main(argv: Sequence[str] | None = None) -> int:
    """``lp3d eval`` on its own; exit status 0, 1 (an error, one line) or
    2 (usage), as :mod:`lp3d.errors` says."""
    return run_command(build_parser(), None if argv is None else list(argv))
