"""Export a trained encoder to an ONNX model package (``lp3d export``; ``docs/model-package.md``).

The modules: :mod:`~lp3d.export.onnx` (the encoder to ONNX, checked against PyTorch with
onnxruntime), :mod:`~lp3d.export.superres` (a super-resolution network in a package),
:mod:`~lp3d.export.weights` (the torch weights file, float16 rounding, the plane basis cut) and
:mod:`~lp3d.export.package` (:func:`export_package`: the whole package, written at once). The command line
is :mod:`lp3d.cli.export`.

May import :mod:`lp3d.training` (checkpoints and the student), :mod:`lp3d.superres_fit` (a fitted
SR) and the layers below them; needs torch (the ``train`` extra).
"""

from lp3d.export.package import (
    ExportError,
    ExportOptions,
    ExportResult,
    ParityError,
    SuperresAdded,
    add_superres_to_package,
    add_superres_to_weights,
    check_onnx,
    check_superres_onnx,
    export_encoder,
    export_package,
    export_superres,
    package_superres,
    reduce_plane_basis,
    round_to_float16,
    save_weights,
    store_float16,
)

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
