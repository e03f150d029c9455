"""A super-resolution network in a model package: exported to ONNX (:func:`export_superres`), checked
(:func:`check_superres_onnx`), recorded in the sidecar (:func:`package_superres`) and in the weights file
(:func:`add_superres_to_weights`). Used by :mod:`lp3d.export.package`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from lp3d.atomic import atomic_path, create_temp, discard, publish
from lp3d.export.onnx import (
    MIN_OPSET,
    ExportError,
    ParityError,
    export_batched,
)
from lp3d.lift.model_package import (
    ModelPackageError,
    decoder_digest,
    superres_entry,
    superres_path,
)
from lp3d.lift.superres_weights import folded_weights, superres_weights_path, write_superres_weights
from lp3d.nets.superres import FoldedSuperResolution, SuperResolution
from lp3d.render.npz_reader import read_torch_file


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
    module = _FeaturesToImage(sr).eval()
    cfg = sr.config
    example = torch.zeros(1, cfg.in_channels, cfg.input_resolution, cfg.input_resolution)
    return export_batched(module, example, path, opset=opset, names=("features", "image"))


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
    """Export ``sr`` to ``MODEL.superres.onnx`` beside ``model_path`` and check it with onnxruntime; write
    its folded weights for the GPU renderer to ``MODEL.superres.npz``.

    Returns ``(the sidecar's superres entry, max abs error)``. Raises :class:`ParityError` when the
    error exceeds ``tolerance``: the network is exported and checked under a temporary name and moved
    into place only when it passes, so an existing ``MODEL.superres.onnx`` is then left as it was."""
    path = superres_path(model_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = create_temp(path)
    try:
        export_superres(sr, tmp, opset=opset)
        err = check_superres_onnx(sr, tmp)
        if not err <= tolerance:
            raise ParityError(f"super-resolution ONNX vs PyTorch max abs error {err:.3g} > {tolerance:g}")
    except BaseException:
        discard(tmp)
        raise
    publish(tmp, path)
    cfg = sr.config
    weights = write_superres_weights(
        superres_weights_path(path),
        folded_weights(FoldedSuperResolution(sr.eval())),
        input_resolution=cfg.input_resolution,
    )
    entry = superres_entry(
        path,
        weights,
        input_resolution=cfg.input_resolution,
        output_resolution=cfg.output_resolution,
        in_channels=cfg.in_channels,
        about={**(about or {}), "config": cfg.to_dict(), "onnx_max_abs_error": err},
    )
    return entry, err


def superres_weights(sr: SuperResolution) -> dict[str, Any]:
    """The ``superres`` entry of an inference-weights file (float32: the network is small)."""
    return {
        "config": sr.config.to_dict(),
        "state": {k: v.detach().cpu().float().clone() for k, v in sr.state_dict().items()},
    }


def add_superres_to_weights(path: str | os.PathLike[str], sr: SuperResolution, decoder_sha256: str) -> Path:
    """Add (or replace) the ``superres`` entry of an existing inference-weights file written by
    :func:`save_weights`, atomically; its decoder must be the one the SR was made for."""
    path = Path(path)
    try:
        data = read_torch_file(path, "an inference-weights file")
    except (OSError, ValueError) as e:
        raise ExportError(f"--weights {e}") from None
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
    data["superres"] = superres_weights(sr)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return path


def fitted_superres(
    path: str, decoder_sha256: str, allow_worse: bool
) -> tuple[SuperResolution, dict[str, Any]]:
    """The SR of a finished ``lp3d.superres_fit.fit`` checkpoint, checked against the model's decoder and
    its own held-out score; ``(network, about)``."""
    from lp3d.superres_fit.fit import FitError, load_fit

    try:
        fit = load_fit(path)
    except FitError as e:
        raise ExportError(f"--superres: {e}") from None
    if not fit.finished:
        raise ExportError(
            f"--superres {fit.path}: the fit stopped at step {fit.step} of {fit.config.steps}; run the same "
            "python -m lp3d.superres_fit command again to finish it"
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
        "source": "python -m lp3d.superres_fit",
        "fit_checkpoint": str(fit.path),
        "fit_config": fit.config.to_dict(),
        "heldout": {k: v for k, v in report.items() if k != "per_pair"},
    }
    return fit.superres, about
