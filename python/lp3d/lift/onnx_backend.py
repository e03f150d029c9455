"""The ``onnx`` backend of :func:`lp3d.lift.inference.load_encoder`: an ``.onnx`` encoder (and the
package's super-resolution network) run by ONNX Runtime on the CPU, its input and output shapes
checked against the sidecar.

May import :mod:`lp3d.lift.model_package`, :mod:`lp3d.lift.loaded` and :mod:`lp3d.render`;
onnxruntime only when a model is loaded."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lp3d.lift.loaded import LoadedEncoder, LoadedSuperres, reshape_planes
from lp3d.lift.model_package import (
    ModelPackage,
    ModelPackageError,
    SuperresEntry,
    load_model_package,
    verify_superres_file,
)
from lp3d.render.settings import N_CHANNELS


def _ort_session(path: Path) -> Any:
    """An onnxruntime CPU session of ``path``; clear errors for a missing onnxruntime or a bad file."""
    try:
        import onnxruntime as ort
    except ImportError as e:
        raise ModelPackageError(
            f"the onnx backend needs onnxruntime (pip install onnxruntime): {e}"
        ) from None
    options = ort.SessionOptions()
    options.log_severity_level = 3  # errors only: warnings about unused initialisers are noise here
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types (InvalidProtobuf, Fail, ...)
        raise ModelPackageError(f"{path}: cannot load the ONNX model ({type(e).__name__}: {e})") from None


def _run_session(session: Any, feeds: dict[str, np.ndarray], where: object) -> np.ndarray:
    """The first output of ``session`` on ``feeds``; onnxruntime's own errors (a graph that fails on
    its input, a shape it cannot take) as a :class:`ModelPackageError` naming the model."""
    try:
        return session.run(None, feeds)[0]
    except Exception as e:  # onnxruntime raises its own types (Fail, InvalidArgument, RuntimeException)
        raise ModelPackageError(f"{where}: the ONNX model failed to run ({type(e).__name__}: {e})") from None


def _check_output(path: Path, output: Any, resolution: int) -> None:
    """The graph's declared output, (B, 3, 32, T, T) or (B, 96, T, T), agrees with the sidecar's
    ``triplane_resolution`` T (a symbolic dimension is checked on every run instead)."""
    shape, t = list(output.shape), resolution
    fits = len(shape) in (4, 5)
    if fits:
        channels, sides = shape[1:-2], shape[-2:]
        known = all(isinstance(d, int) for d in channels)
        fits = not (known and channels not in ([3 * N_CHANNELS], [3, N_CHANNELS]))
        fits = fits and all(d == t for d in sides if isinstance(d, int))
    if not fits:
        raise ModelPackageError(
            f"{path}: output {output.name!r} has shape {shape}, but the package says "
            f"(B, 3, {N_CHANNELS}, {t}, {t})"
        )


def load_onnx_superres(package: ModelPackage, entry: SuperresEntry) -> LoadedSuperres:
    """The package's SR network from its ONNX file, checked against the sidecar's entry."""
    verify_superres_file(entry)
    session = _ort_session(entry.path)
    import onnxruntime as ort  # present: the session was made

    where = f"{entry.path} (the package's 'superres')"
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1 or len(outputs) != 1:
        raise ModelPackageError(
            f"{where}: expected one input (features) and one output (image), found {len(inputs)} and "
            f"{len(outputs)}"
        )
    c, r, ro = entry.in_channels, entry.input_resolution, entry.output_resolution
    for what, shape, want in (
        ("input", inputs[0].shape, (c, r, r)),
        ("output", outputs[0].shape, (3, ro, ro)),
    ):
        dims = ", ".join(map(str, want))
        if len(shape) != 4 or any(
            isinstance(d, int) and d != w for d, w in zip(shape[1:], want, strict=True)
        ):
            raise ModelPackageError(
                f"{where}: {what} has shape {list(shape)}, but the sidecar says (B, {dims})"
            )
    name = inputs[0].name
    fixed_batch = inputs[0].shape[0] if isinstance(inputs[0].shape[0], int) else None

    def run(features: np.ndarray) -> np.ndarray:
        if fixed_batch is not None and features.shape[0] != fixed_batch:
            if fixed_batch != 1:
                raise ModelPackageError(f"{where}: the model only accepts batches of exactly {fixed_batch}")
            return np.concatenate([run(features[i : i + 1]) for i in range(features.shape[0])])
        return _run_session(session, {name: features}, where)

    return LoadedSuperres(
        package,
        "onnx",
        r,
        ro,
        c,
        f"{entry.path.name} (onnxruntime {ort.__version__}, CPU)",
        run,
        where,
    )


def load_onnx_encoder(path: Path, *, superres: bool = False) -> LoadedEncoder:
    """The ``onnx`` backend of :func:`lp3d.lift.inference.load_encoder`: ``path`` and its sidecar."""
    package = load_model_package(path)
    if not path.is_file():
        raise ModelPackageError(f"{path}: no such model file")
    session = _ort_session(path)
    import onnxruntime as ort  # present: the session was made

    inputs = session.get_inputs()
    if len(inputs) != 1:
        raise ModelPackageError(f"{path}: expected one input (the image), found {len(inputs)}")
    inp = inputs[0]
    shape = list(inp.shape)
    s = package.image_size
    if len(shape) != 4 or shape[1] not in (3, "3") or any(isinstance(d, int) and d != s for d in shape[2:]):
        raise ModelPackageError(
            f"{path}: input {inp.name!r} has shape {shape}, but the package says (B, 3, {s}, {s})"
        )
    fixed_batch = shape[0] if isinstance(shape[0], int) else None
    outputs = session.get_outputs()
    if len(outputs) != 1:
        raise ModelPackageError(f"{path}: expected one output (the planes), found {len(outputs)}")
    _check_output(path, outputs[0], package.triplane_resolution)

    def run(images: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(images, dtype=np.float32)
        if fixed_batch is not None and x.shape[0] != fixed_batch:
            # Exported with a static batch: run that many at a time.
            if fixed_batch != 1:
                raise ModelPackageError(f"{path}: the model only accepts batches of exactly {fixed_batch}")
            return np.concatenate([run(x[i : i + 1]) for i in range(x.shape[0])])
        out = _run_session(session, {inp.name: x}, path)
        return reshape_planes(out, x.shape[0], str(path), package.triplane_resolution)

    sr = load_onnx_superres(package, package.superres) if superres and package.superres else None
    return LoadedEncoder(package, "onnx", run, f"{path.name} (onnxruntime {ort.__version__}, CPU)", sr)
