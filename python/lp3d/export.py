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
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.encoder import LP3DEncoder
from lp3d.model_package import save_model_package
from lp3d.train import CheckpointError, Student, load_checkpoint, student_from_checkpoint

__all__ = ["ExportError", "check_onnx", "export_encoder", "main", "save_weights"]

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
    args = p.parse_args(argv)
    try:
        ckpt = load_checkpoint(args.checkpoint)
        student = student_from_checkpoint(ckpt, "cpu")
        path = export_encoder(student, args.output, opset=args.opset)
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
    print(f"wrote {sidecar} (decoder weights and scene bounds; lp3d encode --model {path})")
    if args.weights:
        weights = save_weights(student, args.weights)
        print(f"wrote {weights} (float16 inference weights; lp3d encode --backend torch --model {weights})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
