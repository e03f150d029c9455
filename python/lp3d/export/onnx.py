"""The encoder to ONNX: :func:`export_encoder` (a checkpoint's student or a bare encoder, dynamic batch)
and :func:`check_onnx` (onnxruntime against PyTorch), with the errors of an export. Used by
:mod:`lp3d.export.package`, which re-exports these names.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_path
from lp3d.nets.encoder import LP3DEncoder
from lp3d.training.student import Student

#: Highest opset torch's TorchScript exporter (``dynamo=False``) writes; a higher one is its
#: traceback, not a file.
MAX_OPSET = 20
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
    encoder = _as_module(model).eval()
    s = encoder.config.image_size
    example = torch.zeros(1, 3, s, s, device=next(encoder.parameters()).device)
    return export_batched(encoder, example, path, opset=opset, names=("image", "triplane"))


def export_batched(
    module: nn.Module, example: Tensor, path: str | os.PathLike[str], *, opset: int, names: tuple[str, str]
) -> Path:
    """``module`` as ONNX at ``path`` (its folder made, written atomically): one input and one output,
    named ``names``, traced from ``example`` with the batch axis dynamic. Used for the encoder and the
    super-resolution network."""
    if not MIN_OPSET <= opset <= MAX_OPSET:
        raise ValueError(f"opset must be in [{MIN_OPSET}, {MAX_OPSET}] (what the exporter writes): {opset}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # legacy-exporter deprecation and tracer shape warnings
        torch.onnx.export(
            module,
            (example,),
            str(tmp),
            dynamo=False,
            opset_version=opset,
            input_names=[names[0]],
            output_names=[names[1]],
            dynamic_axes={names[0]: {0: "batch"}, names[1]: {0: "batch"}},
        )
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
