"""What ``lp3d encode --refine`` buys on heads whose truth is known: held-out procedural-teacher
identities, each rendered as a photo and lifted exactly as ``lp3d encode`` lifts a photo (face found,
aligned, its camera from the landmarks, the shipped model's encoder, then ``--refine`` at its default
through the package's super-resolution network), scored at ``lp3d eval``'s novel views against the
teacher.

    python bench/refine_teachers.py [--n-identities 8] [--steps 60]

Identities are teacher seeds ``eval_seed_start + 200 ..`` (outside ``lp3d eval``'s and
``bench/refine_sweep.py``'s, so nothing here was tuned on them); input yaws spread over ±35° as
``lp3d eval`` spreads them, pitch and the rest of the camera drawn as its inputs are. Each photo is a
512² render (RGB, 48+48 samples); novel views are raw 128² renders of the lifted head and of the
teacher at EG3D's 48+48, PSNR by ``lp3d.render.psnr.psnr_db``. Printed: per identity, the camera found
against the true one and the novel-view PSNR of the encoder and of the refined head; then means and a
Markdown table.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

import lp3d_render
from lp3d.evaluation.protocol import NOVEL_VIEWS, input_camera, input_yaws
from lp3d.images import rgb_to_uint8
from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
from lp3d.lift.pose import camera_at
from lp3d.lift.refine import RefineSettings, refine, superres_module
from lp3d.photo import prepare_photo, to_encoder_input
from lp3d.render.camera import camera_summary, look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.teachers.procedural import ProceduralTeacher
from lp3d.training.config import TRAIN_CONFIGS

#: What ``--camera`` names, as the table's caption says it.
CAMERAS = {
    "face": "from the face",
    "fit": "fitted from the face",
    "search": "searched photometrically",
    "true": "of the true camera",
}
#: Samples of every render here: EG3D's.
SAMPLES = {"depth_resolution": 48, "depth_resolution_importance": 48}


def novel_psnr(head: object, truth: object, cams: np.ndarray, sr: object) -> tuple[float, float]:
    """Mean PSNR over ``cams`` of ``head`` against ``truth``: its raw 128² render against the truth's
    128², and its super-resolved image (``sr`` of its raw feature image, as ``lp3d render`` shows it)
    against the truth's render at the SR's output size."""
    raw = lp3d_render.render(head, cams, resolution=128, outputs=["rgb"], **SAMPLES)["rgb"]
    ref = lp3d_render.render(truth, cams, resolution=128, outputs=["rgb"], **SAMPLES)["rgb"]
    feats = lp3d_render.render(head, cams, resolution=sr.input_resolution, outputs=["features"], **SAMPLES)
    big = sr(feats["features"])
    ref_big = lp3d_render.render(truth, cams, resolution=sr.output_resolution, outputs=["rgb"], **SAMPLES)[
        "rgb"
    ]
    n = len(cams)
    return (
        statistics.fmean(psnr_db(raw[i], ref[i]) for i in range(n)),
        statistics.fmean(psnr_db(big[i], ref_big[i]) for i in range(n)),
    )


# Long because: one identity's whole path (render, prepare, encode, refine, score) reads best in order.
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n-identities", type=int, default=8)
    p.add_argument("--steps", type=int, default=RefineSettings().steps)
    p.add_argument("--no-superres", action="store_true", help="refine the raw render only")
    p.add_argument(
        "--camera",
        choices=("face", "fit", "search", "true"),
        default="face",
        help="where the refine starts: the face's camera as it is (lp3d encode --refine's way), fitted "
        "photometrically from the face's first (as for a video's next frame), searched photometrically "
        "without the face's (a grid, then the fit: refine without a pose), or the true camera",
    )
    p.add_argument(
        "--fit-camera",
        action="store_true",
        help="move the camera with the planes (RefineSettings.fit_camera)",
    )
    args = p.parse_args(argv)

    cfg = TRAIN_CONFIGS["small-colour"]
    teacher = ProceduralTeacher()
    encoder = load_encoder(DEFAULT_MODEL, superres=True)
    pkg = encoder.package
    superres = None if args.no_superres else superres_module(pkg)
    settings = RefineSettings(steps=args.steps, fit_camera=args.fit_camera)
    views = np.stack([look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in NOVEL_VIEWS])
    seeds = [cfg.eval_seed_start + 200 + i for i in range(args.n_identities)]
    rows = []
    for seed, yaw in zip(seeds, input_yaws(args.n_identities), strict=True):
        truth = teacher.sample(seed)
        truth_gpu = truth.to_native()
        cam, _ = input_camera(cfg, seed, float(yaw))
        photo = rgb_to_uint8(
            lp3d_render.render(truth_gpu, cam, resolution=512, outputs=["rgb"], **SAMPLES)["rgb"]
        )
        try:
            prep = prepare_photo(photo, pkg.image_size, detect=True, name=f"identity {seed}")
        except ValueError as e:  # every camera's rows are the heads whose face was found
            print(f"identity {seed}: skipped ({e})", file=sys.stderr)
            continue
        face = prep.pose
        if args.camera == "true":
            # The true camera is the render's: the photo is lifted as rendered (in the training
            # framing), not re-framed by the landmarks, whose crop would move it.
            prep = prepare_photo(photo, pkg.image_size, detect=False, name=f"identity {seed}")
        lifted = pkg.triplane(encoder.encode(to_encoder_input(prep.image[None]))[0], source="bench")
        t0 = time.perf_counter()
        true = camera_summary(cam)
        if args.camera == "fit":
            start = camera_at(*face).double().numpy()
            result = refine(lifted, prep.image, settings, start_camera=start, superres=superres)
        elif args.camera == "search":
            result = refine(lifted, prep.image, settings, superres=superres)
        else:
            known = {"camera": cam} if args.camera == "true" else {"pose": face}
            result = refine(lifted, prep.image, settings, superres=superres, **known)
        seconds = time.perf_counter() - t0
        base = novel_psnr(lifted.to_native(), truth_gpu, views, encoder.superres)
        refined = novel_psnr(result.triplane.to_native(), truth_gpu, views, encoder.superres)
        rows.append((seed, true["yaw_deg"], face, base, refined, seconds))
        print(
            f"identity {seed}: true yaw {true['yaw_deg']:+.1f}° pitch {true['pitch_deg']:+.1f}°, from the "
            f"face {face[0]:+.1f}° {face[1]:+.1f}°, refined at {result.yaw_deg:+.1f}° "
            f"{result.pitch_deg:+.1f}°; novel views raw {base[0]:.2f} -> "
            f"{refined[0]:.2f} dB, super-resolved {base[1]:.2f} -> {refined[1]:.2f} dB "
            f"({seconds:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
    if not rows:
        print("no identity had a face found", file=sys.stderr)
        return 1
    how = "raw render only" if superres is None else "last steps through the SR"
    flags = (" --no-superres" if args.no_superres else "") + f" --camera {args.camera}"
    flags += " --fit-camera" if args.fit_camera else ""
    print(
        f"\nCommand: `python bench/refine_teachers.py --n-identities {args.n_identities} --steps {args.steps}"
        f"{flags}` ({time.strftime('%Y-%m-%d')}; {len(rows)} of "
        f"{args.n_identities} held-out teacher identities with a face found; refine {args.steps} steps, "
        f"{how}, starting at the camera {CAMERAS[args.camera]})\n"
    )
    print("| novel views | encoder | refined | gain (mean) | gain (min / max) |\n|---|---:|---:|---:|---:|")
    for k, name in enumerate(("raw 128²", f"super-resolved {encoder.superres.output_resolution}²")):
        gains = [r[4][k] - r[3][k] for r in rows]
        print(
            f"| {name} | {statistics.fmean(r[3][k] for r in rows):.2f} dB | "
            f"{statistics.fmean(r[4][k] for r in rows):.2f} dB | {statistics.fmean(gains):+.2f} dB | "
            f"{min(gains):+.2f} / {max(gains):+.2f} dB |"
        )
    print(f"\nrefine time per head (median): {statistics.median(r[5] for r in rows):.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
