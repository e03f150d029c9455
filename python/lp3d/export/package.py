"""Export a trained encoder to ONNX and check it against PyTorch with onnxruntime.

``lp3d export runs/t/checkpoints/step-000200.pt -o model.onnx`` writes the encoder
``image (B, 3, S, S) in [-1, 1] -> triplane (B, 3, 32, T, T)`` (dynamic batch, opset 17 by default),
then runs it in onnxruntime on seeded random images and compares with the PyTorch encoder: the
largest absolute difference on the triplane must be <= ``--tolerance`` (default 1e-3), else the
command fails (exit 1) and nothing is written: the package is made in a hidden folder beside ``-o`` and
moved into place only once every check has passed, so a failed export leaves an existing model at the
destination as it was. ``-o``, its sidecar, its super-resolution file and ``--weights`` must be distinct
files, none of them the checkpoint (or ``--superres``) it reads.

**Super-resolution.** When the model has a trained super-resolution network (SR), it is exported
beside the encoder as ``MODEL.superres.onnx`` (``features (B, 32, R, R) -> image (B, 3, R_out,
R_out)``, dynamic batch), checked against PyTorch with onnxruntime the same way (the largest absolute
difference on the image <= ``--tolerance``), and recorded in the sidecar's ``superres`` entry with its
SHA-256. Its source: ``--superres FIT.pt`` (a network fitted by
``python -m lp3d.superres_fit``), else the checkpoint's own SR when the paper recipe trained
one; the CPU recipe trains none. The exported
graph is :class:`lp3d.nets.superres.FoldedSuperResolution` (the constant-w styles folded into plain
convolutions), compared with the unfolded network. An existing package gains an SR without
re-exporting its encoder::

    lp3d export --superres runs/sr/superres-fit.pt --package python/lp3d/models/small.onnx \\
        --weights python/lp3d/models/small.pt

The ONNX graph holds the encoder only. The decoder weights and scene bounds a renderer needs go into
the model package's JSON sidecar, ``<model>.json`` (:mod:`lp3d.lift.model_package`), written beside the
``.onnx``; ``lp3d encode --model <model>.onnx`` reads both.

The TorchScript-based exporter is used (``dynamo=False``): it needs only the ``onnx`` package, while the
dynamo exporter also needs ``onnxscript``.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from lp3d.atomic import publish_all
from lp3d.errors import UsageError, UserError, run_command
from lp3d.export.onnx import (
    MIN_OPSET,
    ExportError,
    ParityError,
    check_onnx,
    export_encoder,
)
from lp3d.export.superres import (
    add_superres_to_weights,
    check_superres_onnx,
    export_superres,
    fitted_superres,
    package_superres,
)
from lp3d.export.weights import (
    check_rounding,
    reduce_plane_basis,
    round_to_float16,
    save_weights,
    store_float16,
    training_inputs,
)
from lp3d.lift.model_package import (
    ModelPackageError,
    decoder_digest,
    load_model_package,
    save_model_package,
    set_package_superres,
    sidecar_path,
    superres_path,
)
from lp3d.nets.superres import SuperResolution
from lp3d.outputs import check_distinct
from lp3d.training.checkpoint import CheckpointError, load_checkpoint, student_from_checkpoint
from lp3d.training.student import Student

__all__ = [
    "ExportError",
    "ParityError",
    "add_superres_to_weights",
    "check_onnx",
    "check_superres_onnx",
    "export_encoder",
    "export_superres",
    "main",
    "package_superres",
    "reduce_plane_basis",
    "round_to_float16",
    "save_weights",
    "store_float16",
]


def _add_superres_main(args: argparse.Namespace) -> int:
    """``--superres FIT.pt --package MODEL.onnx``: give an existing package a fitted SR."""
    try:
        package = load_model_package(args.package)
        digest = decoder_digest(package.decoder)
        sr, about = fitted_superres(args.superres, digest, args.allow_worse_superres)
        entry, err = package_superres(
            sr, package.model_path, about=about, opset=args.opset, tolerance=args.tolerance
        )
        sidecar = set_package_superres(package.sidecar, entry)
        weights = add_superres_to_weights(args.weights, sr, digest) if args.weights else None
    except (ModelPackageError, ExportError, ValueError) as e:
        raise UserError(str(e)) from None  # run_command prints it as "lp3d export: error: ..."
    _print_superres(entry, err, args.tolerance)
    print(f"updated {sidecar} (its 'superres' entry)")
    if weights is not None:
        print(f"updated {weights} (its 'superres' entry, for --backend torch)")
    return 0


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


#: ``--help``'s description (``lp3d export`` and ``python -m lp3d.export``).
DESCRIPTION = __doc__.splitlines()[0]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The export options, shared by ``lp3d export`` and ``python -m lp3d.export``."""
    p.add_argument(
        "checkpoint",
        nargs="?",
        default=None,
        help="training checkpoint (.pt) or run directory (its latest checkpoint); leave out with --package",
    )
    p.add_argument("-o", "--output", default=None, help="ONNX file to write (with a checkpoint)")
    p.add_argument("--opset", type=int, default=MIN_OPSET, help=f"ONNX opset (>= {MIN_OPSET})")
    p.add_argument(
        "--tolerance", type=float, default=1e-3, help="max abs error allowed on the triplane / image"
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
        help="package this super-resolution network (a python -m lp3d.superres_fit checkpoint) "
        "instead of the checkpoint's own",
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


def build_parser(prog: str = "python -m lp3d.export") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=run_cli)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.export`` (an alias of ``lp3d export``); exit status 0, 1 (an error, one line,
    including a failed parity check) or 2 (usage), as :mod:`lp3d.errors` says."""
    return run_command(build_parser(), argv)


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


def _choose_superres(
    args: argparse.Namespace, ckpt: dict[str, Any], student: Student, notes: list[str]
) -> tuple[SuperResolution | None, dict[str, Any]]:
    """The SR to package and where it came from: ``--superres FIT.pt``, else the paper recipe's own,
    else none (with a note)."""
    if args.superres is not None:
        return fitted_superres(
            args.superres, decoder_digest(student.decoder.weights()), args.allow_worse_superres
        )
    if not args.no_superres and student.config.recipe == "paper":
        return student.superres, {
            "source": "training checkpoint",
            "checkpoint": str(ckpt["path"]),
            "step": ckpt.get("step"),
        }
    if not args.no_superres:
        notes.append(
            "no super-resolution network: the CPU recipe trains none (fit one with "
            "python -m lp3d.superres_fit, then add it with --superres FIT.pt --package MODEL.onnx)"
        )
    return None, {}


def _shrink_student(
    args: argparse.Namespace, ckpt: dict[str, Any], student: Student, notes: list[str]
) -> None:
    """``--basis-components`` and ``--float16``, in place, each with a note of what it changed."""
    if args.basis_components is not None:
        images = training_inputs(student.config, ckpt["teacher"], args.data_cache)
        change = reduce_plane_basis(student, images, args.basis_components)
        notes.append(
            f"plane basis reduced to {args.basis_components} planes over {len(images)} training inputs: "
            f"the triplane changes by at most {change:.3g}"
        )
    if args.float16:
        reference = copy.deepcopy(student)
        change = round_to_float16(student)
        err16 = check_rounding(reference, student)
        notes.append(
            f"weights rounded to float16 (largest change of a weight {change:.3g}; of the triplane "
            f"{err16:.3g})"
        )


def _check_paths(args: argparse.Namespace, checkpoint: str | None) -> None:
    """Refuse, before any work, an output that would replace an input or another output: ``-o``, its
    sidecar, its super-resolution file and ``--weights`` against the ``checkpoint`` file read (None in
    the ``--package`` mode), ``--superres`` and ``--package``. UserError naming the flags."""
    inputs: list[tuple[str, Path]] = [] if checkpoint is None else [("checkpoint", Path(checkpoint))]
    if args.superres is not None:
        inputs.append(("--superres", Path(args.superres)))
    outputs: list[tuple[str, Path]] = []
    if args.output is not None:
        out = Path(args.output)
        if out.suffix.lower() == ".json":
            raise UserError(
                f"-o {out}: a model file must not end in .json (the name of its sidecar); use MODEL.onnx"
            )
        if out.is_dir():
            raise UserError(f"-o {out} is a folder; give a file name such as {out / 'model.onnx'}")
        outputs += [("-o", out), ("its sidecar", sidecar_path(out))]
        outputs.append(("its super-resolution model", superres_path(out)))
    if args.package is not None:
        inputs.append(("--package", Path(args.package)))
        outputs.append(("its super-resolution model", superres_path(args.package)))
    if args.weights is not None:
        outputs.append(("--weights", Path(args.weights)))
    check_distinct(inputs, outputs)


@contextlib.contextmanager
def _staging_folder(output: Path) -> Iterator[Path]:
    """A new hidden folder beside ``output`` (same file system: its files can be renamed into place),
    deleted with whatever is left in it."""
    output.parent.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix=".lp3d-export-", suffix=".tmp", dir=output.parent))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _write_package(
    args: argparse.Namespace, student: Student, sr: SuperResolution | None, about: dict[str, Any], path: Path
) -> tuple[float, dict[str, Any] | None, float]:
    """The package at ``path`` (a staging folder): encoder, checked; SR, checked; sidecar. Returns
    ``(encoder error, superres entry or None, its error)``; ParityError when a check fails."""
    export_encoder(student, path, opset=args.opset)
    if args.float16:
        store_float16(path)
    err = check_onnx(student, path)
    if not err <= args.tolerance:
        raise ParityError(f"ONNX vs PyTorch max abs error {err:.3g} > {args.tolerance:g}")
    sr_entry, sr_err = None, float("nan")
    if sr is not None:
        sr_entry, sr_err = package_superres(sr, path, about=about, opset=args.opset, tolerance=args.tolerance)
    cfg = student.config
    save_model_package(
        path, student.decoder.weights(), cfg.encoder, student.scene, output_name="triplane", superres=sr_entry
    )
    return err, sr_entry, sr_err


def _export_package(args: argparse.Namespace, notes: list[str]) -> tuple[Student, Any, tuple[Any, ...]]:
    """Load, check and write the package; moved into place only once every check has passed."""
    ckpt = load_checkpoint(args.checkpoint)
    _check_paths(args, ckpt["path"])  # a run directory: the checkpoint file it resolved to
    student = student_from_checkpoint(ckpt, "cpu")
    sr, about = _choose_superres(args, ckpt, student, notes)
    _shrink_student(args, ckpt, student, notes)
    out = Path(args.output)
    with _staging_folder(out) as folder:
        result = _write_package(args, student, sr, about, folder / out.name)
        names = [superres_path(out).name] if result[1] is not None else []
        names += [out.name, sidecar_path(out).name]  # the sidecar last: it names the others
        publish_all([(folder / name, out.parent / name) for name in names])
    return student, sr, result


def run_cli(args: argparse.Namespace) -> int:
    """Export with parsed :func:`add_arguments` options; returns the exit status."""
    if _check_usage(args) == "add-superres":
        _check_paths(args, None)
        return _add_superres_main(args)
    _check_paths(args, args.checkpoint)
    notes: list[str] = []
    try:
        student, sr, (err, sr_entry, sr_err) = _export_package(args, notes)
    except ParityError as e:
        raise UserError(f"{e}; nothing written ({args.output} left as it was)") from None
    except (CheckpointError, ValueError, ExportError) as e:
        raise UserError(str(e)) from None
    cfg, path = student.config, args.output
    print(
        f"wrote {path} (encoder {cfg.name!r}, image (B, 3, {cfg.image_size}, {cfg.image_size}) -> triplane "
        f"(B, 3, 32, {cfg.triplane_resolution}, {cfg.triplane_resolution}), opset {args.opset}); "
        f"onnxruntime vs PyTorch max abs error {err:.2e} <= {args.tolerance:g}"
    )
    if sr_entry is not None:
        _print_superres(sr_entry, sr_err, args.tolerance)
    for note in notes:
        print(note)
    print(f"wrote {sidecar_path(path)} (decoder weights and scene bounds; lp3d encode --model {path})")
    if args.weights:
        weights = save_weights(student, args.weights, superres=sr)
        print(f"wrote {weights} (float16 inference weights; lp3d encode --backend torch --model {weights})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
