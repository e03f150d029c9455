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

import contextlib
import copy
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lp3d.atomic import publish_all
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
    decoder_digest,
    load_model_package,
    save_model_package,
    set_package_superres,
    sidecar_path,
    superres_path,
)
from lp3d.lift.superres_weights import superres_weights_path
from lp3d.nets.superres import SuperResolution
from lp3d.outputs import check_distinct
from lp3d.training.checkpoint import load_checkpoint, student_from_checkpoint
from lp3d.training.student import Student

__all__ = [
    "ExportError",
    "ExportOptions",
    "ExportResult",
    "ParityError",
    "SuperresAdded",
    "add_superres_to_package",
    "add_superres_to_weights",
    "check_onnx",
    "check_superres_onnx",
    "export_encoder",
    "export_package",
    "export_superres",
    "package_superres",
    "reduce_plane_basis",
    "round_to_float16",
    "save_weights",
    "store_float16",
]


@dataclass(frozen=True)
class ExportOptions:
    """How :func:`export_package` writes a package (``lp3d export``'s flags of the same names)."""

    opset: int = MIN_OPSET
    #: Largest absolute difference allowed between onnxruntime and PyTorch (triplane; SR image).
    tolerance: float = 1e-3
    #: Store the ONNX weights as float16 (checked against the float16-rounded PyTorch model).
    float16: bool = False
    #: Keep this many planes of the plane basis (CPU configurations); None keeps them all.
    basis_components: int | None = None
    #: Where the run's synthetic dataset is cached (for ``basis_components``).
    data_cache: str | None = None
    #: A fitted SR (``lp3d superres-fit``'s ``superres-fit.pt``) to package instead of the checkpoint's.
    superres: str | None = None
    no_superres: bool = False
    allow_worse_superres: bool = False


@dataclass
class ExportResult:
    """What :func:`export_package` wrote, and what its checks found."""

    output: Path
    sidecar: Path
    student: Student
    encoder_error: float
    superres_entry: dict[str, Any] | None
    superres_error: float
    weights: Path | None
    notes: list[str] = field(default_factory=list)


@dataclass
class SuperresAdded:
    """What :func:`add_superres_to_package` changed."""

    entry: dict[str, Any]
    error: float
    sidecar: Path
    weights: Path | None


def add_superres_to_package(
    package: str | os.PathLike[str],
    superres: str | os.PathLike[str],
    *,
    weights: str | os.PathLike[str] | None = None,
    options: ExportOptions | None = None,
) -> SuperresAdded:
    """Give an existing model ``package`` (MODEL.onnx) the SR fitted in ``superres`` (FIT.pt), checked
    against PyTorch, and add it to the torch ``weights`` file when given. Raises
    :class:`ModelPackageError`, :class:`ExportError` or ValueError (nothing written on a failed check),
    and ValueError (from :func:`lp3d.outputs.check_distinct`) for paths that would replace an input."""
    options = options if options is not None else ExportOptions(superres=str(superres))
    _check_paths(None, None, superres=superres, package=package, weights=weights)
    loaded = load_model_package(package)
    digest = decoder_digest(loaded.decoder)
    sr, about = fitted_superres(superres, digest, options.allow_worse_superres)
    entry, err = package_superres(
        sr, loaded.model_path, about=about, opset=options.opset, tolerance=options.tolerance
    )
    sidecar = set_package_superres(loaded.sidecar, entry)
    written = add_superres_to_weights(weights, sr, digest) if weights else None
    return SuperresAdded(entry, err, Path(sidecar), None if written is None else Path(written))


def export_package(
    checkpoint: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    weights: str | os.PathLike[str] | None = None,
    options: ExportOptions | None = None,
) -> ExportResult:
    """Export ``checkpoint`` (a training checkpoint or run folder) to the model package ``output``
    (MODEL.onnx with its MODEL.json, and MODEL.superres.onnx when there is an SR), each graph checked
    against PyTorch with onnxruntime; the package is written whole, or not at all. ``weights``: also
    write the float16 torch weights file. Raises :class:`ParityError` (a failed check: nothing
    written), :class:`CheckpointError`, :class:`ExportError` or ValueError."""
    options = options if options is not None else ExportOptions()
    _check_paths(output, checkpoint, superres=options.superres, weights=weights)
    notes: list[str] = []
    ckpt = load_checkpoint(checkpoint)
    # A run directory: check again against the checkpoint file it resolved to.
    _check_paths(output, ckpt["path"], superres=options.superres, weights=weights)
    student = student_from_checkpoint(ckpt, "cpu")
    sr, about = _choose_superres(options, ckpt, student, notes)
    _shrink_student(options, ckpt, student, notes)
    out = Path(output)
    with _staging_folder(out) as folder:
        err, sr_entry, sr_err = _write_package(options, student, sr, about, folder / out.name)
        sr_file = superres_path(out)
        names = [sr_file.name, superres_weights_path(sr_file).name] if sr_entry is not None else []
        names += [out.name, sidecar_path(out).name]  # the sidecar last: it names the others
        publish_all([(folder / name, out.parent / name) for name in names])
    written = Path(save_weights(student, weights, superres=sr)) if weights else None
    return ExportResult(out, sidecar_path(out), student, err, sr_entry, sr_err, written, notes)


def _choose_superres(
    args: ExportOptions, ckpt: dict[str, Any], student: Student, notes: list[str]
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


def _shrink_student(args: ExportOptions, ckpt: dict[str, Any], student: Student, notes: list[str]) -> None:
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


def _check_paths(
    output: str | os.PathLike[str] | None,
    checkpoint: str | os.PathLike[str] | None,
    *,
    superres: str | os.PathLike[str] | None = None,
    package: str | os.PathLike[str] | None = None,
    weights: str | os.PathLike[str] | None = None,
) -> None:
    """Refuse, before any work, an output that would replace an input or another output: ``-o``
    (``output``), its sidecar, its super-resolution file and ``--weights`` against the ``checkpoint``
    file read (None in the ``--package`` mode), ``--superres`` and ``--package``. ValueError naming
    the flags."""
    inputs: list[tuple[str, Path]] = [] if checkpoint is None else [("checkpoint", Path(checkpoint))]
    if superres is not None:
        inputs.append(("--superres", Path(superres)))
    outputs: list[tuple[str, Path]] = []
    if output is not None:
        out = Path(output)
        if out.suffix.lower() == ".json":
            raise ValueError(
                f"-o {out}: a model file must not end in .json (the name of its sidecar); use MODEL.onnx"
            )
        if out.is_dir():
            raise ValueError(f"-o {out} is a folder; give a file name such as {out / 'model.onnx'}")
        outputs += [("-o", out), ("its sidecar", sidecar_path(out))]
        outputs.append(("its super-resolution model", superres_path(out)))
        outputs.append(("its super-resolution weights", superres_weights_path(superres_path(out))))
    if package is not None:
        inputs.append(("--package", Path(package)))
        outputs.append(("its super-resolution model", superres_path(package)))
        outputs.append(("its super-resolution weights", superres_weights_path(superres_path(package))))
    if weights is not None:
        outputs.append(("--weights", Path(weights)))
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
    args: ExportOptions, student: Student, sr: SuperResolution | None, about: dict[str, Any], path: Path
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
