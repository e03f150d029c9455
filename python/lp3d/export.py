"""Export a trained encoder to ONNX and check it against PyTorch with onnxruntime.

``python -m lp3d.export runs/t/checkpoints/step-000200.pt -o model.onnx`` writes the encoder
``image (B, 3, S, S) in [-1, 1] -> triplane (B, 3, 32, T, T)`` (dynamic batch, opset 17 by default),
then runs it in onnxruntime on seeded random images and compares with the PyTorch encoder: the
largest absolute difference on the triplane must be <= ``--tolerance`` (default 1e-3), else the
command fails (exit 1) and the file is not kept.

The ONNX graph holds the encoder only. The decoder weights and scene bounds a renderer needs go into
the model package's JSON sidecar, ``<model>.json`` (:mod:`lp3d.model_package`), written beside the
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
from lp3d.encoder import LP3DEncoder
from lp3d.model_package import save_model_package
from lp3d.train import CheckpointError, Student, load_checkpoint, student_from_checkpoint

__all__ = [
    "ExportError",
    "check_onnx",
    "export_encoder",
    "main",
    "reduce_plane_basis",
    "round_to_float16",
    "save_weights",
    "store_float16",
]

#: Lowest opset accepted (LayerNorm and the attention ops export as single nodes from 17 on).
MIN_OPSET = 17


class ExportError(RuntimeError):
    """The ONNX model disagrees with PyTorch, or cannot be made."""


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
    atomically. A :class:`~lp3d.train.Student` exports ``Student.encode`` (encoder + offset)."""
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


def save_weights(student: Student, path: str | os.PathLike[str], *, half: bool = True) -> Path:
    """The student's inference weights as a plain ``torch.load(weights_only=True)`` dict that
    ``lp3d encode --backend torch --model PATH`` reads: ``config`` (EncoderConfig), ``encoder`` (state
    dict), ``plane_offset`` (or None), ``decoder`` {w0, b0, w1, b1} and ``bounds``. ``half`` stores the
    encoder and offset in float16 (half the size; they load back into float32 parameters)."""
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
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return path


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
    from lp3d.synthetic_data import SyntheticDataset, default_cache_root
    from lp3d.train import build_teacher, dataset_key

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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m lp3d.export", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="training checkpoint (.pt) or run directory (its latest checkpoint)")
    p.add_argument("-o", "--output", required=True, help="ONNX file to write")
    p.add_argument("--opset", type=int, default=MIN_OPSET, help=f"ONNX opset (>= {MIN_OPSET})")
    p.add_argument("--tolerance", type=float, default=1e-3, help="max abs error allowed on the triplane")
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
    args = p.parse_args(argv)
    notes: list[str] = []
    try:
        ckpt = load_checkpoint(args.checkpoint)
        student = student_from_checkpoint(ckpt, "cpu")
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
            sidecar = save_model_package(
                path, student.decoder.weights(), student.config.encoder, student.scene, output_name="triplane"
            )
    except (CheckpointError, ValueError, ExportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cfg = student.config
    if not err <= args.tolerance:
        Path(path).unlink(missing_ok=True)
        print(
            f"error: ONNX vs PyTorch max abs error {err:.3g} > {args.tolerance:g}; removed {path}",
            file=sys.stderr,
        )
        return 1
    print(
        f"wrote {path} (encoder {cfg.name!r}, image (B, 3, {cfg.image_size}, {cfg.image_size}) -> triplane "
        f"(B, 3, 32, {cfg.triplane_resolution}, {cfg.triplane_resolution}), opset {args.opset}); "
        f"onnxruntime vs PyTorch max abs error {err:.2e} <= {args.tolerance:g}"
    )
    for note in notes:
        print(note)
    print(f"wrote {sidecar} (decoder weights and scene bounds; lp3d encode --model {path})")
    if args.weights:
        weights = save_weights(student, args.weights)
        print(f"wrote {weights} (float16 inference weights; lp3d encode --backend torch --model {weights})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
