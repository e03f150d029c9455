"""Export a trained encoder to ONNX and check it against PyTorch with onnxruntime.

``lp3d export runs/t/checkpoints/step-000200.pt -o model.onnx`` writes the encoder
``image (B, 3, S, S) in [-1, 1] -> triplane (B, 3, 32, T, T)`` (dynamic batch, opset 17 by default),
then runs it in onnxruntime on seeded random images and compares with the PyTorch encoder: the
largest absolute difference on the triplane must be <= ``--tolerance`` (default 1e-3), else the
command fails (exit 1) and the file is not kept.

**Super-resolution.** When the model has a trained super-resolution network (SR), it is exported
beside the encoder as ``MODEL.superres.onnx`` (``features (B, 32, R, R) -> image (B, 3, R_out,
R_out)``, dynamic batch), checked against PyTorch with onnxruntime the same way (the largest absolute
difference on the image <= ``--tolerance``), and recorded in the sidecar's ``superres`` entry with its
SHA-256. Its source: ``--superres FIT.pt`` (a network fitted by
``python -m lp3d.training.superres_fit``), else the checkpoint's own SR when the paper recipe trained
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
import copy
import dataclasses
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.errors import EXIT_ERROR, UsageError, run_command
from lp3d.lift.model_package import (
    ModelPackageError,
    decoder_digest,
    load_model_package,
    save_model_package,
    set_package_superres,
    superres_entry,
    superres_path,
)
from lp3d.nets.encoder import LP3DEncoder
from lp3d.nets.superres import FoldedSuperResolution, SuperResolution
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

#: Lowest opset accepted (LayerNorm and the attention ops export as single nodes from 17 on).
MIN_OPSET = 17


class ExportError(RuntimeError):
    """The ONNX model disagrees with PyTorch, or cannot be made."""


class ParityError(ExportError):
    """onnxruntime and PyTorch disagree by more than the tolerance (exit status 1)."""


class StudentEncoder(nn.Module):
    """``image (B, 3, S, S) -> triplane (B, 3, 32, T, T)`` of a student: its encoder plus, when the
    configuration has one, the mean-triplane offset (``Student.encode``)."""

    def __init__(self, student: Student) -> None:
        super().__init__()
        self.student = student
        self.config = student.config.encoder

    def forward(self, image: Tensor) -> Tensor:
        return self.student.encode(image)


def _as_module(model: LP3DEncoder | Student) -> nn.Module:
    return StudentEncoder(model) if isinstance(model, Student) else model


def export_encoder(
    model: LP3DEncoder | Student, path: str | os.PathLike[str], *, opset: int = MIN_OPSET
) -> Path:
    """Write the encoder of ``model`` as ONNX (input ``image``, output ``triplane``, dynamic batch),
    atomically. A :class:`~lp3d.training.student.Student` exports ``Student.encode`` (encoder +
    offset)."""
    if opset < MIN_OPSET:
        raise ValueError(f"opset must be >= {MIN_OPSET}, got {opset}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    encoder = _as_module(model).eval()
    s = encoder.config.image_size
    example = torch.zeros(1, 3, s, s, device=next(encoder.parameters()).device)
    with atomic_path(path) as tmp, warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # TracerWarnings about shape checks that are constant here
        torch.onnx.export(
            encoder,
            (example,),
            str(tmp),
            dynamo=False,
            opset_version=opset,
            input_names=["image"],
            output_names=["triplane"],
            dynamic_axes={"image": {0: "batch"}, "triplane": {0: "batch"}},
        )
    return path


class _FeaturesToImage(nn.Module):
    """``features -> image`` of a folded SR (a module of its own so the exporter sees one input)."""

    def __init__(self, sr: SuperResolution) -> None:
        super().__init__()
        self.folded = FoldedSuperResolution(sr.eval())

    def forward(self, features: Tensor) -> Tensor:
        return self.folded(features)


def export_superres(sr: SuperResolution, path: str | os.PathLike[str], *, opset: int = MIN_OPSET) -> Path:
    """Write ``sr`` as ONNX: input ``features`` (B, C, R, R), output ``image`` (B, 3, R_out, R_out),
    dynamic batch, atomically. The graph is the folded form (plain convolutions; same outputs)."""
    if opset < MIN_OPSET:
        raise ValueError(f"opset must be >= {MIN_OPSET}, got {opset}")
    path = Path(path)
    module = _FeaturesToImage(sr).eval()
    cfg = sr.config
    example = torch.zeros(1, cfg.in_channels, cfg.input_resolution, cfg.input_resolution)
    with atomic_path(path) as tmp, warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # legacy-exporter deprecation and tracer warnings
        torch.onnx.export(
            module,
            (example,),
            str(tmp),
            dynamo=False,
            opset_version=opset,
            input_names=["features"],
            output_names=["image"],
            dynamic_axes={"features": {0: "batch"}, "image": {0: "batch"}},
        )
    return path


def check_superres_onnx(
    sr: SuperResolution, path: str | os.PathLike[str], *, batch: int = 2, seed: int = 0
) -> float:
    """Max absolute difference between onnxruntime and the (unfolded) PyTorch SR on seeded features
    uniform in [-1, 1] (the range of the renderer's features), (batch, C, R, R)."""
    import onnxruntime as ort

    cfg = sr.config
    g = torch.Generator().manual_seed(seed)
    r = cfg.input_resolution
    features = torch.rand(batch, cfg.in_channels, r, r, generator=g) * 2 - 1
    with torch.no_grad():
        expected = sr.eval()(features).float().numpy()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (got,) = session.run(["image"], {"features": features.numpy()})
    if got.shape != expected.shape:
        raise ExportError(f"SR ONNX output shape {got.shape} != PyTorch {expected.shape}")
    return float(np.max(np.abs(got - expected)))


def package_superres(
    sr: SuperResolution,
    model_path: str | os.PathLike[str],
    *,
    about: dict[str, Any] | None = None,
    opset: int = MIN_OPSET,
    tolerance: float = 1e-3,
) -> tuple[dict[str, Any], float]:
    """Export ``sr`` to ``MODEL.superres.onnx`` beside ``model_path`` and check it with onnxruntime.

    Returns ``(the sidecar's superres entry, max abs error)``. Raises :class:`ParityError` (and removes
    the file) when the error exceeds ``tolerance``."""
    path = export_superres(sr, superres_path(model_path), opset=opset)
    err = check_superres_onnx(sr, path)
    if not err <= tolerance:
        path.unlink(missing_ok=True)
        raise ParityError(
            f"super-resolution ONNX vs PyTorch max abs error {err:.3g} > {tolerance:g}; removed {path}"
        )
    cfg = sr.config
    entry = superres_entry(
        path,
        input_resolution=cfg.input_resolution,
        output_resolution=cfg.output_resolution,
        in_channels=cfg.in_channels,
        about={**(about or {}), "config": cfg.to_dict(), "onnx_max_abs_error": err},
    )
    return entry, err


def _superres_weights(sr: SuperResolution) -> dict[str, Any]:
    """The ``superres`` entry of an inference-weights file (float32: the network is small)."""
    return {
        "config": sr.config.to_dict(),
        "state": {k: v.detach().cpu().float().clone() for k, v in sr.state_dict().items()},
    }


def save_weights(
    student: Student,
    path: str | os.PathLike[str],
    *,
    half: bool = True,
    superres: SuperResolution | None = None,
) -> Path:
    """The student's inference weights as a plain ``torch.load(weights_only=True)`` dict that
    ``lp3d encode --backend torch --model PATH`` reads: ``config`` (EncoderConfig), ``encoder`` (state
    dict), ``plane_offset`` (or None), ``decoder`` {w0, b0, w1, b1} and ``bounds``, and with
    ``superres`` its ``{"config", "state"}`` (float32). ``half`` stores the encoder and offset in
    float16 (half the size; they load back into float32 parameters)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def cast(t: Tensor) -> Tensor:
        t = t.detach().cpu()
        return t.half() if half and t.is_floating_point() else t.clone()

    w0, b0, w1, b1 = (t.detach().cpu().clone() for t in student.decoder.weights())
    scene = student.scene
    data = {
        "format": "lp3d-encoder-weights-v1",
        "config": student.config.encoder.to_dict(),
        "encoder": {k: cast(v) for k, v in student.encoder.state_dict().items()},
        "plane_offset": None if student.plane_offset is None else cast(student.plane_offset),
        "decoder": {"w0": w0, "b0": b0, "w1": w1, "b1": b1},
        "bounds": {"box_warp": scene.box_warp, "ray_start": scene.ray_start, "ray_end": scene.ray_end},
    }
    if superres is not None:
        data["superres"] = _superres_weights(superres)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return path


def add_superres_to_weights(path: str | os.PathLike[str], sr: SuperResolution, decoder_sha256: str) -> Path:
    """Add (or replace) the ``superres`` entry of an existing inference-weights file written by
    :func:`save_weights`, atomically; its decoder must be the one the SR was made for."""
    path = Path(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for non-checkpoints
        raise ExportError(
            f"--weights {path}: cannot be read as a plain state-dict checkpoint ({e})"
        ) from None
    if not isinstance(data, dict) or data.get("format") != "lp3d-encoder-weights-v1":
        raise ExportError(f"--weights {path}: not an lp3d inference-weights file (lp3d-encoder-weights-v1)")
    try:
        same = decoder_digest(data.get("decoder", {})) == decoder_sha256
    except ModelPackageError as e:
        raise ExportError(f"--weights {path}: {e}") from None
    if not same:
        raise ExportError(
            f"--weights {path}: its decoder is not the one the super-resolution network was fit for"
        )
    data["superres"] = _superres_weights(sr)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return path


def _fitted_superres(
    path: str, decoder_sha256: str, allow_worse: bool
) -> tuple[SuperResolution, dict[str, Any]]:
    """The SR of a finished ``lp3d.training.superres_fit`` checkpoint, checked against the model's decoder and
    its own held-out score; ``(network, about)``."""
    from lp3d.training.superres_fit import FitError, load_fit

    try:
        fit = load_fit(path)
    except FitError as e:
        raise ExportError(f"--superres: {e}") from None
    if not fit.finished:
        raise ExportError(
            f"--superres {fit.path}: the fit stopped at step {fit.step} of {fit.config.steps}; run the same "
            "python -m lp3d.training.superres_fit command again to finish it"
        )
    if fit.model.get("decoder_sha256") != decoder_sha256:
        raise ExportError(
            f"--superres {fit.path}: fitted for a model with another decoder ({fit.model.get('path')}); its "
            "feature images are not this model's"
        )
    report = fit.report or {}
    if not report.get("gain_db", 0.0) > 0 and not allow_worse:
        ours, bilinear = (float(report.get(k, float("nan"))) for k in ("superres_psnr", "bilinear_psnr"))
        raise ExportError(
            f"--superres {fit.path}: on its held-out pairs the SR ({ours:.2f} dB) does not beat bilinear "
            f"upsampling of the raw render ({bilinear:.2f} dB); not worth shipping (--allow-worse-superres "
            "to export it anyway)"
        )
    about = {
        "source": "python -m lp3d.training.superres_fit",
        "fit_checkpoint": str(fit.path),
        "fit_config": fit.config.to_dict(),
        "heldout": {k: v for k, v in report.items() if k != "per_pair"},
    }
    return fit.superres, about


@torch.no_grad()
def round_to_float16(student: Student) -> float:
    """Round the encoder's weights and the plane offset to float16 values (kept as float32 tensors), as
    the shipped files store them; returns the largest change of a weight. Exporting after this makes
    the float16 ONNX file and the float16 torch weights hold exactly the same numbers."""
    worst = 0.0
    params = [*student.encoder.parameters()] + (
        [student.plane_offset] if student.plane_offset is not None else []
    )
    for p in params:
        rounded = p.half().float()
        worst = max(worst, float((rounded - p).abs().max()))
        p.copy_(rounded)
    return worst


def store_float16(path: str | os.PathLike[str], *, min_elements: int = 1024) -> Path:
    """Rewrite an ONNX file so its float32 initializers of at least ``min_elements`` values are stored
    as float16 and cast back to float32 by a ``Cast`` node (half the file; onnxruntime folds the casts
    when it loads the model, so inference still runs in float32). Atomic."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    path = Path(path)
    model = onnx.load(str(path))
    graph = model.graph
    casts = []
    for init in list(graph.initializer):
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < min_elements:
            continue
        stored = numpy_helper.from_array(
            numpy_helper.to_array(init).astype(np.float16), f"{init.name}.float16"
        )
        graph.initializer.remove(init)
        graph.initializer.append(stored)
        casts.append(helper.make_node("Cast", [stored.name], [init.name], to=TensorProto.FLOAT))
    for i, node in enumerate(casts):  # before their consumers: nodes stay topologically sorted
        graph.node.insert(i, node)
    onnx.checker.check_model(model)
    with atomic_path(path) as tmp:
        onnx.save(model, str(tmp))
    return path


@torch.no_grad()
def reduce_plane_basis(student: Student, images: Tensor, components: int) -> float:
    """Keep ``components`` planes of the student's plane basis: the rank-``components`` approximation of
    its output that is best (least squares) over ``images`` (N, 3, S, S), folded into the weights.

    The basis adds ``c(I) · P`` (c: K coefficients, P: K planes). Over the images, the centred outputs
    ``(c - c̄) · P`` have principal directions V; the reduced basis is the first ``components`` of them,
    its coefficients ``c · P · Vᵀ`` (a linear map folded into the coefficient MLP's last layer), and
    the part of the mean output ``c̄ · P`` outside V moves into the constant plane offset (exact: the
    upsampling is linear). Returns the largest change of a triplane value over ``images``.
    """
    basis = student.encoder.basis
    if basis is None or student.plane_offset is None:
        raise ValueError("reduce_plane_basis needs a student with a plane basis and a plane offset")
    k = basis.components.shape[0]
    if not 1 <= components <= k:
        raise ValueError(f"components must be in [1, {k}], got {components}")
    before = student.encode(images)
    if components == k:
        return 0.0
    captured: dict[str, Tensor] = {}
    handle = basis.coefficients.register_forward_hook(lambda m, i, o: captured.setdefault("c", o))
    student.encode(images[:1])  # warm the hook's shape path
    captured.clear()
    student.encode(images)
    handle.remove()
    c = captured["c"].double()  # (N, K)
    planes = basis.components.double().reshape(k, -1)  # (K, D)
    mean_c = c.mean(0)
    _, _, vh = torch.linalg.svd((c - mean_c) @ planes, full_matrices=False)
    v = vh[:components]  # (K', D), orthonormal rows
    project = planes @ v.T  # (K, K'): new coefficients = c · project
    mean_out = mean_c @ planes
    residual = mean_out - (mean_out @ v.T) @ v  # (D,): the constant part V does not hold
    last = basis.coefficients[-1]
    assert isinstance(last, nn.Linear)
    new_last = nn.Linear(last.in_features, components).to(last.weight)
    new_last.weight.copy_((project.T @ last.weight.double()).to(last.weight))
    new_last.bias.copy_((project.T @ last.bias.double()).to(last.bias))
    basis.coefficients[-1] = new_last
    shape = basis.components.shape[1:]
    basis.components = nn.Parameter(v.reshape(components, *shape).to(basis.components))
    t = student.config.encoder.triplane_resolution
    const = residual.reshape(1, *shape).float()
    if shape[-1] != t:
        const = torch.nn.functional.interpolate(const, size=(t, t), mode="bilinear", align_corners=False)
    student.plane_offset.add_(const.reshape(student.plane_offset.shape))
    cfg = dataclasses.replace(student.config.encoder, basis_components=components)
    student.encoder.config = cfg
    student.config = dataclasses.replace(student.config, encoder=cfg)
    return float((student.encode(images) - before).abs().max())


@torch.no_grad()
def check_rounding(reference: Student, rounded: Student, *, batch: int = 2, seed: int = 0) -> float:
    """Max absolute triplane difference between two students on seeded images (e.g. float32 weights
    against the same rounded to float16)."""
    s = reference.config.image_size
    image = torch.rand(batch, 3, s, s, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    return float((reference.eval().encode(image) - rounded.eval().encode(image)).abs().max())


def _training_inputs(cfg: Any, teacher_name: str, data_cache: str | None, n: int = 256) -> Tensor:
    """The first ``n`` encoder inputs of the run's cached synthetic dataset (CPU recipe)."""
    from lp3d.training.synthetic_data import SyntheticDataset, default_cache_root
    from lp3d.training.teacher_factory import build_teacher, dataset_key

    if cfg.recipe != "cpu" or teacher_name != "procedural":
        raise ValueError("--basis-components needs a CPU-recipe run of the procedural teacher")
    teacher = build_teacher(teacher_name, triplane_resolution=cfg.triplane_resolution)
    key = dataset_key(cfg, teacher, teacher_name)
    root = Path(data_cache) if data_cache else default_cache_root()
    try:
        data = SyntheticDataset.load(root / key.digest(), key)
    except ValueError as e:
        raise ValueError(
            f"--basis-components needs the run's cached dataset ({e}); run python -m lp3d.train on this "
            "machine first, or pass --data-cache"
        ) from None
    return torch.from_numpy(data.ref_image[:n].astype(np.float32))


def check_onnx(
    model: LP3DEncoder | Student, path: str | os.PathLike[str], *, batch: int = 2, seed: int = 0
) -> float:
    """Max absolute difference between onnxruntime and PyTorch on seeded images (batch, 3, S, S)."""
    import onnxruntime as ort

    encoder = _as_module(model)
    s = encoder.config.image_size
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, s, s, generator=g) * 2 - 1
    device = next(encoder.parameters()).device
    with torch.no_grad():
        expected = encoder.eval()(image.to(device)).float().cpu().numpy()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (got,) = session.run(["triplane"], {"image": image.numpy()})
    if got.shape != expected.shape:
        raise ExportError(f"ONNX output shape {got.shape} != PyTorch {expected.shape}")
    return float(np.max(np.abs(got - expected)))


def _add_superres_main(args: argparse.Namespace) -> int:
    """``--superres FIT.pt --package MODEL.onnx``: give an existing package a fitted SR."""
    try:
        package = load_model_package(args.package)
        digest = decoder_digest(package.decoder)
        sr, about = _fitted_superres(args.superres, digest, args.allow_worse_superres)
        entry, err = package_superres(
            sr, package.model_path, about=about, opset=args.opset, tolerance=args.tolerance
        )
        sidecar = set_package_superres(package.sidecar, entry)
        weights = add_superres_to_weights(args.weights, sr, digest) if args.weights else None
    except (ModelPackageError, ExportError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ERROR
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


#: ``--help``'s description (``lp3d export`` and ``python -m lp3d.training.export``).
DESCRIPTION = __doc__.splitlines()[0]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The export options, shared by ``lp3d export`` and ``python -m lp3d.training.export``."""
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
        help="package this super-resolution network (a python -m lp3d.training.superres_fit checkpoint) "
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


def build_parser(prog: str = "python -m lp3d.training.export") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=run_cli)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.training.export`` (an alias of ``lp3d export``); exit status 0, 1 (an error, one line,
    including a failed parity check) or 2 (usage), as :mod:`lp3d.errors` says."""
    return run_command(build_parser(), argv)


def run_cli(args: argparse.Namespace) -> int:
    """Export with parsed :func:`add_arguments` options; returns the exit status."""
    if args.checkpoint is None:
        if args.package is None or args.superres is None:
            raise UsageError("give a CHECKPOINT and -o MODEL.onnx, or --superres FIT.pt --package MODEL.onnx")
        if args.output or args.float16 or args.basis_components is not None or args.no_superres:
            raise UsageError(
                "--package adds a super-resolution network only; -o, --float16, --basis-components and "
                "--no-superres need a CHECKPOINT"
            )
        return _add_superres_main(args)
    if args.output is None:
        raise UsageError("-o/--output is required with a CHECKPOINT")
    if args.package is not None:
        raise UsageError(
            "--package is for adding a super-resolution network to an existing package (no CHECKPOINT)"
        )
    if args.superres is not None and args.no_superres:
        raise UsageError("--superres and --no-superres exclude each other")
    notes: list[str] = []
    sr: SuperResolution | None = None
    sr_entry: dict[str, Any] | None = None
    sr_err = float("nan")
    about: dict[str, Any] = {}
    try:
        ckpt = load_checkpoint(args.checkpoint)
        student = student_from_checkpoint(ckpt, "cpu")
        if args.superres is not None:
            sr, about = _fitted_superres(
                args.superres, decoder_digest(student.decoder.weights()), args.allow_worse_superres
            )
        elif not args.no_superres and student.config.recipe == "paper":
            sr = student.superres
            about = {
                "source": "training checkpoint",
                "checkpoint": str(ckpt["path"]),
                "step": ckpt.get("step"),
            }
        elif not args.no_superres:
            notes.append(
                "no super-resolution network: the CPU recipe trains none (fit one with python -m "
                "lp3d.training.superres_fit, then add it with --superres FIT.pt --package MODEL.onnx)"
            )
        if args.basis_components is not None:
            images = _training_inputs(student.config, ckpt["teacher"], args.data_cache)
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
        path = export_encoder(student, args.output, opset=args.opset)
        if args.float16:
            store_float16(path)
        err = check_onnx(student, path)
        if err <= args.tolerance:
            if sr is not None:
                sr_entry, sr_err = package_superres(
                    sr, path, about=about, opset=args.opset, tolerance=args.tolerance
                )
            sidecar = save_model_package(
                path,
                student.decoder.weights(),
                student.config.encoder,
                student.scene,
                output_name="triplane",
                superres=sr_entry,
            )
    except ParityError as e:
        Path(args.output).unlink(missing_ok=True)  # no package without its super-resolution network
        print(f"error: {e}; removed {args.output}", file=sys.stderr)
        return EXIT_ERROR
    except (CheckpointError, ValueError, ExportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ERROR
    cfg = student.config
    if not err <= args.tolerance:
        Path(path).unlink(missing_ok=True)
        print(
            f"error: ONNX vs PyTorch max abs error {err:.3g} > {args.tolerance:g}; removed {path}",
            file=sys.stderr,
        )
        return EXIT_ERROR
    print(
        f"wrote {path} (encoder {cfg.name!r}, image (B, 3, {cfg.image_size}, {cfg.image_size}) -> triplane "
        f"(B, 3, 32, {cfg.triplane_resolution}, {cfg.triplane_resolution}), opset {args.opset}); "
        f"onnxruntime vs PyTorch max abs error {err:.2e} <= {args.tolerance:g}"
    )
    if sr_entry is not None:
        _print_superres(sr_entry, sr_err, args.tolerance)
    for note in notes:
        print(note)
    print(f"wrote {sidecar} (decoder weights and scene bounds; lp3d encode --model {path})")
    if args.weights:
        weights = save_weights(student, args.weights, superres=sr)
        print(f"wrote {weights} (float16 inference weights; lp3d encode --backend torch --model {weights})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
