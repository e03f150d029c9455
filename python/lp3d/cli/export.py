"""``lp3d export`` (and ``python -m lp3d.export``): export a training checkpoint to an ONNX model
package with :func:`lp3d.export.export_package`, or give an existing package a fitted
super-resolution network with :func:`lp3d.export.add_superres_to_package`.

The library needs torch (the ``train`` extra), so it is imported only when this subcommand is parsed
or run."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from lp3d.errors import UsageError, UserError, run_command

HELP = "export a checkpoint to an ONNX model package (needs torch)"
#: This subcommand's options import torch: the top-level parser adds them only when it is named.
LAZY = True
DESCRIPTION = "Export a trained encoder to ONNX and check it against PyTorch with onnxruntime."


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The export options, shared by ``lp3d export`` and ``python -m lp3d.export``."""
    from lp3d.errors import float_in, int_in
    from lp3d.export.onnx import MAX_OPSET, MIN_OPSET

    p.add_argument(
        "checkpoint",
        nargs="?",
        default=None,
        help="training checkpoint (.pt) or run directory (its latest checkpoint); leave out with --package",
    )
    p.add_argument("-o", "--output", default=None, help="ONNX file to write (with a checkpoint)")
    p.add_argument(
        "--opset",
        type=int_in(MIN_OPSET, MAX_OPSET),
        default=MIN_OPSET,
        help=f"ONNX opset ({MIN_OPSET} to {MAX_OPSET})",
    )
    p.add_argument(
        "--tolerance",
        type=float_in(0.0, 1.0),
        default=1e-3,
        help="max abs error allowed on the triplane / image, in [0, 1]",
    )
    p.add_argument(
        "--weights", default=None, help="also write the inference weights (float16 .pt) for the torch backend"
    )
    p.add_argument(
        "--float16",
        action="store_true",
        help="store the ONNX weights as float16 (half the file); the check then compares with the "
        "float16-rounded PyTorch model, and the rounding's own effect is printed",
    )
    p.add_argument(
        "--basis-components",
        type=int,
        default=None,
        help="keep this many planes of the encoder's plane basis (CPU configurations): the best "
        "approximation over the run's cached training inputs; the change it makes is printed",
    )
    p.add_argument("--data-cache", default=None, help="where the run's synthetic dataset is cached")
    p.add_argument(
        "--superres",
        default=None,
        metavar="FIT.pt",
        help="package this super-resolution network (a lp3d superres-fit checkpoint) instead of the "
        "checkpoint's own",
    )
    p.add_argument(
        "--no-superres", action="store_true", help="export no super-resolution network, even a trained one"
    )
    p.add_argument(
        "--package",
        default=None,
        metavar="MODEL.onnx",
        help="with --superres and no checkpoint: add the network to this existing package (and to --weights "
        "if given) without re-exporting the encoder",
    )
    p.add_argument(
        "--allow-worse-superres",
        action="store_true",
        help="export a fitted SR even if it does not beat bilinear upsampling on its held-out pairs",
    )


def _check_usage(args: argparse.Namespace) -> str:
    """``"add-superres"`` (no CHECKPOINT: add an SR to a package) or ``"export"``; UsageError for flags
    that do not go together."""
    if args.checkpoint is None:
        if args.package is None or args.superres is None:
            raise UsageError("give a CHECKPOINT and -o MODEL.onnx, or --superres FIT.pt --package MODEL.onnx")
        if args.output or args.float16 or args.basis_components is not None or args.no_superres:
            raise UsageError(
                "--package adds a super-resolution network only; -o, --float16, --basis-components and "
                "--no-superres need a CHECKPOINT"
            )
        return "add-superres"
    if args.output is None:
        raise UsageError("-o/--output is required with a CHECKPOINT")
    if args.package is not None:
        raise UsageError(
            "--package is for adding a super-resolution network to an existing package (no CHECKPOINT)"
        )
    if args.superres is not None and args.no_superres:
        raise UsageError("--superres and --no-superres exclude each other")
    return "export"


def _print_superres(entry: dict[str, Any], err: float, tolerance: float) -> None:
    r, ro = entry["input_resolution"], entry["output_resolution"]
    print(
        f"wrote super-resolution {entry['model']} (features (B, 32, {r}, {r}) -> image (B, 3, {ro}, {ro})); "
        f"onnxruntime vs PyTorch max abs error {err:.2e} <= {tolerance:g}"
    )
    held = entry.get("about", {}).get("heldout")
    if held:
        print(
            f"  held-out: SR {held['superres_psnr']:.2f} dB PSNR vs bilinear upsampling "
            f"{held['bilinear_psnr']:.2f} dB ({held['gain_db']:+.2f} dB over {held['pairs']} pairs)"
        )


def run(args: argparse.Namespace) -> int:
    """Export with parsed :func:`add_arguments` options; prints what was written; returns the exit status."""
    from lp3d.export import ExportError, ExportOptions, ParityError, add_superres_to_package, export_package
    from lp3d.lift.model_package import ModelPackageError
    from lp3d.training.checkpoint import CheckpointError

    mode = _check_usage(args)
    options = ExportOptions(
        opset=args.opset,
        tolerance=args.tolerance,
        float16=args.float16,
        basis_components=args.basis_components,
        data_cache=args.data_cache,
        superres=args.superres,
        no_superres=args.no_superres,
        allow_worse_superres=args.allow_worse_superres,
    )
    if mode == "add-superres":
        try:
            added = add_superres_to_package(
                args.package, args.superres, weights=args.weights, options=options
            )
        except (ModelPackageError, ExportError, ValueError) as e:
            raise UserError(str(e)) from None  # run_command prints it as "lp3d export: error: ..."
        _print_superres(added.entry, added.error, args.tolerance)
        print(f"updated {added.sidecar} (its 'superres' entry)")
        if added.weights is not None:
            print(f"updated {added.weights} (its 'superres' entry, for --backend torch)")
        return 0
    try:
        result = export_package(args.checkpoint, args.output, weights=args.weights, options=options)
    except ParityError as e:
        raise UserError(f"{e}; nothing written ({args.output} left as it was)") from None
    except (CheckpointError, ValueError, ExportError) as e:
        raise UserError(str(e)) from None
    cfg, path = result.student.config, args.output
    print(
        f"wrote {path} (encoder {cfg.name!r}, image (B, 3, {cfg.image_size}, {cfg.image_size}) -> triplane "
        f"(B, 3, 32, {cfg.triplane_resolution}, {cfg.triplane_resolution}), opset {args.opset}); "
        f"onnxruntime vs PyTorch max abs error {result.encoder_error:.2e} <= {args.tolerance:g}"
    )
    if result.superres_entry is not None:
        _print_superres(result.superres_entry, result.superres_error, args.tolerance)
    for note in result.notes:
        print(note)
    print(f"wrote {result.sidecar} (decoder weights and scene bounds; lp3d encode --model {path})")
    if result.weights is not None:
        print(
            f"wrote {result.weights} (float16 inference weights; lp3d encode --backend torch --model "
            f"{result.weights})"
        )
    return 0


def build_parser(prog: str = "python -m lp3d.export") -> argparse.ArgumentParser:
    """This command's parser on its own (as ``lp3d-view``'s is)."""
    from lp3d.cli import standalone_parser

    return standalone_parser(sys.modules[__name__], prog)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m lp3d.export`` (the same as ``lp3d export``); exit status 0, 1 (an error, one line,
    including a failed parity check) or 2 (usage), as :mod:`lp3d.errors` says."""
    return run_command(build_parser(), None if argv is None else list(argv))
