"""``lp3d superres-fit`` (and ``python -m lp3d.superres_fit``): fit a super-resolution network for a
trained encoder whose recipe has none, with :func:`lp3d.superres_fit.fit_superres`.

The library needs torch (the ``train`` extra), so it is imported only when this subcommand is parsed
or run."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

from lp3d.errors import UserError, run_command

HELP = "fit a super-resolution network for a trained encoder (needs torch)"
#: This subcommand's options import torch: the top-level parser adds them only when it is named.
LAZY = True
DESCRIPTION = (
    "Fit a super-resolution network (SR) for a trained encoder whose recipe has none: pairs of the "
    "student's raw renders and the teacher's high-resolution images, made once and cached, then a fit "
    "scored on held-out pairs against bilinear upsampling. Package it with: lp3d export --superres "
    "OUT/superres-fit.pt --package MODEL.onnx."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The fitting options: one flag per :class:`~lp3d.superres_fit.FitConfig` field, plus the inputs
    and outputs."""
    from lp3d.superres_fit import FitConfig, default_pair_cache
    from lp3d.superres_fit.config import TRAIN_ON

    defaults = FitConfig()
    p.add_argument(
        "model",
        nargs="?",
        default=None,
        help="MODEL.onnx (with its MODEL.json), CHECKPOINT.pt or a run folder (default: the shipped model)",
    )
    p.add_argument("--out", required=True, type=Path, help="folder for the checkpoint, log.csv, report.json")
    p.add_argument("--backend", choices=("onnx", "torch"), default=None, help="as for lp3d encode")
    p.add_argument(
        "--cache", type=Path, default=None, help=f"pair cache folder (default: {default_pair_cache()})"
    )
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    for f in fields(FitConfig):
        value = getattr(defaults, f.name)
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, tuple):
            p.add_argument(flag, type=int, nargs="+", default=list(value), help=f"(default: {value})")
        elif f.name == "train_on":
            p.add_argument(flag, choices=TRAIN_ON, default=value, help=f"(default: {value})")
        else:
            p.add_argument(flag, type=type(value), default=value, help=f"(default: {value})")


def run(args: argparse.Namespace) -> int:
    """Fit with parsed :func:`add_arguments` options; returns the exit status."""
    import torch

    from lp3d.lift.model_package import ModelPackageError
    from lp3d.superres_fit import FitConfig, FitError, StalePairsError, fit_superres

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        cfg = FitConfig.from_dict({f.name: getattr(args, f.name) for f in fields(FitConfig)})
        fit_superres(
            args.model, args.out, cfg, backend=args.backend, cache=args.cache, progress=not args.quiet
        )
    except (FitError, StalePairsError, ModelPackageError, ValueError) as e:
        raise UserError(str(e)) from None
    return 0


def build_parser(prog: str = "python -m lp3d.superres_fit") -> argparse.ArgumentParser:
    """This command's parser on its own (as ``lp3d-view``'s is)."""
    from lp3d.cli import standalone_parser

    return standalone_parser(sys.modules[__name__], prog)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m lp3d.superres_fit`` (the same as ``lp3d superres-fit``); exit status 0, 1 (an
    error, one line) or 2 (usage), as :mod:`lp3d.errors` says."""
    return run_command(build_parser(), None if argv is None else list(argv))
