"""A model package's super-resolution network read back from its ONNX file into torch
(:func:`read_superres_onnx`): the :class:`~lp3d.nets.superres.FoldedSuperResolution` that
``lp3d export`` wrote, with gradients, so that ``--refine`` can fit a head through the network that
will show it.

The graph is read by what its operators do, not by the names torch gave its tensors (those change
between exporters): every ``ConvTranspose`` opens a block; in a block, the 3x3 ``Conv`` with one group
is the second convolution, the 1x1 ``Conv`` the ToRGB, and the ``Add`` of a constant (1, C, 1, 1) the
biases in the order the network adds them (after the upsampling FIR, after the convolution, after
ToRGB). The depthwise FIR filters must be the network's fixed ``[1, 3, 3, 1]`` filter. The result is
then run beside onnxruntime on a random feature image; a graph this reading misunderstands is
refused, not trusted.

Needs ``onnx`` and torch (the ``train`` extra)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from lp3d.nets.stylegan_ops import setup_filter
from lp3d.nets.superres import FoldedSuperResolution, SuperresConfig

__all__ = ["PARITY_TOLERANCE", "read_superres_onnx"]

#: Most the torch network read back may differ from onnxruntime on the same random input (float32).
PARITY_TOLERANCE = 1e-4


class SuperresOnnxError(ValueError):
    """The ONNX file is not a folded super-resolution network this reader understands."""


def read_superres_onnx(path: str | os.PathLike[str]) -> FoldedSuperResolution:
    """The folded SR network of the ONNX file at ``path`` (``MODEL.superres.onnx``) as a torch module
    (eval mode, weights frozen). Raises :class:`SuperresOnnxError` (a ValueError) naming the file when
    the graph has another shape or its outputs differ from onnxruntime's."""
    import onnx
    from onnx import numpy_helper

    p = Path(path)
    try:
        model = onnx.load(str(p))
    except Exception as e:  # onnx raises DecodeError, OSError, ...: one message for all
        raise SuperresOnnxError(f"{p}: not a readable ONNX file ({type(e).__name__})") from None
    graph = model.graph
    consts = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    if len(graph.input) != 1:
        raise SuperresOnnxError(f"{p}: expected one input (features), found {len(graph.input)}")
    dims = [d.dim_value for d in graph.input[0].type.tensor_type.shape.dim]
    if len(dims) != 4 or dims[2] != dims[3] or min(dims[1:]) <= 0:
        raise SuperresOnnxError(f"{p}: the input must be features (B, C, R, R), found dims {dims}")

    blocks: list[dict[str, list[np.ndarray]]] = []
    fir = setup_filter().numpy() * 4.0  # symmetric: the flip a true convolution needs is a no-op
    for node in graph.node:
        weights = [consts[i] for i in node.input if i in consts]
        if node.op_type == "ConvTranspose":
            if len(weights) != 1 or weights[0].ndim != 4:
                raise SuperresOnnxError(f"{p}: a ConvTranspose without one constant weight")
            blocks.append({"up": [weights[0].transpose(1, 0, 2, 3)], "conv": [], "rgb": [], "bias": []})
        elif node.op_type == "Conv" and weights:
            group = next((a.i for a in node.attribute if a.name == "group"), 1)
            w = weights[0]
            if group > 1:  # an upsampling FIR: the network's fixed filter, nothing to read
                if w.shape[1:] != (1, *fir.shape) or not np.allclose(w, fir[None, None], atol=1e-6):
                    raise SuperresOnnxError(f"{p}: a depthwise filter that is not the network's FIR")
            elif not blocks:
                raise SuperresOnnxError(f"{p}: a convolution before the first upsampling")
            elif w.shape[-2:] == (3, 3):
                blocks[-1]["conv"].append(w)
            elif w.shape[-2:] == (1, 1):
                blocks[-1]["rgb"].append(w)
            else:
                raise SuperresOnnxError(f"{p}: a convolution of kernel {w.shape[-2:]} has no place here")
        elif node.op_type == "Add" and weights and blocks:
            blocks[-1]["bias"].append(weights[0].reshape(-1))
    if not blocks or any(len(b["conv"]) != 1 or len(b["rgb"]) != 1 or len(b["bias"]) != 3 for b in blocks):
        raise SuperresOnnxError(
            f"{p}: not a folded super-resolution graph (each block needs an up-convolution, a 3x3 "
            "convolution, a ToRGB and three biases)"
        )
    r = dims[2]
    config = SuperresConfig(
        name=p.name,
        in_channels=dims[1],
        input_resolution=r,
        output_resolution=r * 2 ** len(blocks),
        block_channels=tuple(int(b["up"][0].shape[0]) for b in blocks),
    )
    t = lambda a: torch.from_numpy(np.array(a, dtype=np.float32))  # noqa: E731
    try:
        net = FoldedSuperResolution.from_tensors(
            config,
            convs_up=[t(b["up"][0]) for b in blocks],
            biases_up=[t(b["bias"][0]) for b in blocks],
            convs=[t(b["conv"][0]) for b in blocks],
            biases=[t(b["bias"][1]) for b in blocks],
            rgb_weights=[t(b["rgb"][0]) for b in blocks],
            rgb_biases=[t(b["bias"][2]) for b in blocks],
        )
    except ValueError as e:
        raise SuperresOnnxError(f"{p}: its weights do not chain ({e})") from None
    _check_parity(p, net, config)
    return net


def _check_parity(p: Path, net: FoldedSuperResolution, config: SuperresConfig) -> None:
    import onnxruntime as ort

    x = np.random.default_rng(0).standard_normal(
        (1, config.in_channels, config.input_resolution, config.input_resolution), dtype=np.float32
    )
    session = ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
    want = session.run(None, {session.get_inputs()[0].name: x})[0]
    with torch.no_grad():
        got = net(torch.from_numpy(x)).numpy()
    if got.shape != want.shape or not np.abs(got - want).max() <= PARITY_TOLERANCE:
        err = np.abs(got - want).max() if got.shape == want.shape else f"shape {got.shape} vs {want.shape}"
        raise SuperresOnnxError(f"{p}: the graph read back does not reproduce onnxruntime (max diff {err})")
