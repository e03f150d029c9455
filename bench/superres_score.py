"""Score super-resolution fits on the same held-out pairs: those of one model (default: the shipped
one), whatever encoder each fit was made for.

    python bench/superres_score.py runs/sr-small/superres-fit.pt runs/sr-colour/superres-fit.pt

`python -m lp3d.superres_fit` scores a fit on the pairs of the model it was fitted to; this answers
which of two fits is better for one model. The pairs are each fit's configuration's held-out pairs
for ``--model``, from the cache (rendered first when missing). Reported per fit: SR and bilinear
PSNR/SSIM on the student's raw renders and on the teacher's own (`lp3d.superres_fit.train.score`).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from lp3d.superres_fit.checkpoint import load_fit
from lp3d.superres_fit.fit import load_model, open_pairs
from lp3d.superres_fit.train import score


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("fits", type=Path, nargs="+", help="superres-fit.pt checkpoints")
    p.add_argument(
        "--model", type=Path, default=None, help="model package whose pairs score them (default: shipped)"
    )
    args = p.parse_args(argv)
    encoder, info = load_model(args.model, None)
    print(f"pairs of {info['path']} ({info['config_name']})")
    print()
    print(
        "| fit | made for | pairs | student: SR / bilinear PSNR | gain | SSIM SR / bilinear "
        "| teacher's renders: SR / bilinear PSNR | gain |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for path in args.fits:
        fit = load_fit(path)
        with contextlib.redirect_stdout(sys.stderr):  # its "pairs: ..." line, off the table
            _, heldout, _ = open_pairs(fit.config, encoder, None, False)
        r, _ = score(fit.superres, heldout)
        print(
            f"| {path} | {fit.model.get('config_name')} | {r['pairs']} | {r['superres_psnr']:.2f} / "
            f"{r['bilinear_psnr']:.2f} dB | {r['gain_db']:+.2f} dB | {r['superres_ssim']:.3f} / "
            f"{r['bilinear_ssim']:.3f} | {r['teacher_superres_psnr']:.2f} / "
            f"{r['teacher_bilinear_psnr']:.2f} dB | {r['teacher_gain_db']:+.2f} dB |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
