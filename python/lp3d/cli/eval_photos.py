"""``lp3d eval-photos``: is a lifted photo still its person? Lifts each photo of a folder, renders its
novel views and scores them with an independent face-recognition model (:mod:`lp3d.evaluation.photos`).
Writes report.json and identity.png into --out and prints the table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lp3d.cli.common import CLIError, Staged, int_in, parse_samples, progress, resolve_model, say, warn

HELP = "identity and pose of lifted real photos (dlib face recognition; needs torch)"
#: SSIM and --refine import torch: the options are added only when the command line names it.
LAZY = True
DESCRIPTION = (
    "Lift every photo in PHOTOS (a folder or files) with the model, render its head at the novel-view "
    "yaws and measure, per view, whether an independent face-recognition model (dlib's ResNet "
    "descriptors, offline) still finds the photo's person: ID distance (< 0.6 is one person), cosine "
    "similarity, the view's pose error, and the input view's PSNR/SSIM on the face. Writes "
    "report.json and identity.png (photo, views, per-view ID) into --out."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lp3d.evaluation.photos import NOVEL_YAWS_DEG
    from lp3d.lift.refine_settings import MAX_STEPS

    p.add_argument("photos", nargs="+", type=Path, metavar="PHOTOS", help="image files and/or folders")
    p.add_argument("--out", type=Path, required=True, help="output folder (created; must not exist)")
    p.add_argument("--model", type=Path, default=None, help="MODEL.onnx or CHECKPOINT.pt (default: shipped)")
    p.add_argument(
        "--refine",
        type=int_in(0, MAX_STEPS),
        default=0,
        metavar="N",
        help="refine each head for N steps at the camera found from its face (default 0: encoder only)",
    )
    p.add_argument(
        "--samples", type=parse_samples, default=(48, 48), help="coarse+fine samples (default 48+48)"
    )
    p.add_argument(
        "--yaws",
        default=",".join(f"{y:g}" for y in NOVEL_YAWS_DEG),
        help="novel-view yaws in degrees, comma separated (default %(default)s)",
    )


def _yaws(text: str) -> tuple[float, ...]:
    try:
        yaws = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise CLIError(f"--yaws {text!r}: expected degrees separated by commas, e.g. -20,0,20") from None
    if not yaws or not all(-80.0 <= y <= 80.0 for y in yaws):
        raise CLIError(f"--yaws {text!r}: each yaw must be a number in [-80, 80]")
    return yaws


def run(args: argparse.Namespace) -> int:
    from lp3d.cli.encode import collect_images
    from lp3d.evaluation.photos import PhotoSettings, evaluate_photo, figure, summarise, summary_lines
    from lp3d.images import save_png
    from lp3d.lift.inference import load_encoder, load_superres
    from lp3d.photo import PhotoError

    yaws = _yaws(args.yaws)
    if args.out.exists():
        raise CLIError(f"--out {args.out}: exists; name a new folder")
    if not args.out.parent.is_dir():
        raise CLIError(f"--out {args.out}: its parent folder does not exist")
    images = collect_images(args.photos)
    model = resolve_model(args.model)
    encoder = load_encoder(model, None)
    sr = load_superres(model)
    settings = PhotoSettings(refine_steps=args.refine, yaws_deg=yaws, samples=args.samples)
    evals = []
    bar = progress(len(images), "photos", unit="photo")
    try:
        for img in images:
            try:
                evals.append(evaluate_photo(img, encoder, sr, settings))
            except PhotoError as e:
                warn(f"skipped: {e}")
            bar.update()
    finally:
        bar.close()
    if not evals:
        raise CLIError("no photo could be lifted (each was skipped above)")
    summary = summarise(evals)
    report = {
        "model": str(model),
        "refine_steps": args.refine,
        "samples": list(args.samples),
        "summary": summary,
        "photos": [e.to_dict() for e in evals],
    }
    with Staged() as staged:
        staged.mkdir(args.out)
        staged.temp(args.out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        save_png(staged.temp(args.out / "identity.png"), figure(evals))
        written = staged.commit()
    for e in evals:
        ids = ", ".join(
            f"{v.yaw_deg:+.0f}° " + (f"{v.distance:.2f}" if v.distance is not None else "no face")
            for v in e.views
        )
        say(f"{e.name}: camera yaw {e.yaw_deg:+.0f}° pitch {e.pitch_deg:+.0f}°; ID distance {ids}")
    for line in summary_lines(summary):
        say(line)
    for path in written:
        say(f"wrote {path}")
    return 0
