"""Score super-resolution fits on the same held-out pairs: those of one model (default: the shipped
one), whatever encoder each fit was made for.

    python bench/superres_score.py runs/sr-small/superres-fit.pt runs/sr-colour/superres-fit.pt
    python bench/superres_score.py package      # the network the model package ships, on its fit's pairs

`python -m lp3d.superres_fit` scores a fit on the pairs of the model it was fitted to; this answers
which of two fits is better for one model. The pairs are each fit's configuration's held-out pairs
for ``--model``, from the cache (rendered first when missing). ``package`` in place of a checkpoint is
the package's own network (its ONNX file, as ``--refine`` reads it), scored on the held-out pairs of
the fit configuration its sidecar records. Reported per fit: SR and bilinear
PSNR/SSIM on the student's raw renders and on the teacher's own (`lp3d.superres_fit.train.score`).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from lp3d.lift.refine import superres_module
from lp3d.superres_fit.checkpoint import load_fit
from lp3d.superres_fit.config import FitConfig
from lp3d.superres_fit.data import PairSet, pair_keys
from lp3d.superres_fit.fit import load_model, open_pairs
from lp3d.superres_fit.train import score
from lp3d.teachers import ProceduralTeacher


def package_network(encoder: object) -> tuple[object, PairSet, str]:
    """The package's shipped network as a torch module, the held-out pairs of the fit its sidecar
    records, and the configuration's name."""
    pkg = encoder.package  # type: ignore[attr-defined]
    if pkg.superres is None or not pkg.superres.about or "fit_config" not in pkg.superres.about:
        raise SystemExit("the model package has no super-resolution network with a recorded fit")
    cfg = FitConfig.from_dict(pkg.superres.about["fit_config"])
    teacher = ProceduralTeacher(resolution=cfg.teacher_resolution)
    _, heldout_key = pair_keys(cfg, encoder, teacher)
    heldout = PairSet.open(heldout_key, encoder, teacher, root=None, progress=True)
    return superres_module(pkg), heldout, pkg.config_name


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("fits", type=Path, nargs="+", help="superres-fit.pt checkpoints, or 'package'")
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
        if str(path) == "package":
            network, heldout, made_for = package_network(encoder)
        else:
            fit = load_fit(path)
            with contextlib.redirect_stdout(sys.stderr):  # its "pairs: ..." line, off the table
                _, heldout, _ = open_pairs(fit.config, encoder, None, False)
            network, made_for = fit.superres, fit.model.get("config_name")
        r, _ = score(network, heldout)
        print(
            f"| {path} | {made_for} | {r['pairs']} | {r['superres_psnr']:.2f} / "
            f"{r['bilinear_psnr']:.2f} dB | {r['gain_db']:+.2f} dB | {r['superres_ssim']:.3f} / "
            f"{r['bilinear_ssim']:.3f} | {r['teacher_superres_psnr']:.2f} / "
            f"{r['teacher_bilinear_psnr']:.2f} dB | {r['teacher_gain_db']:+.2f} dB |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
