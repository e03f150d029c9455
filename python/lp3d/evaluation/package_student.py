"""The student of a model package, for ``lp3d eval MODEL.onnx`` (or ``MODEL.pt``): a shipped or
exported model scored on held-out identities without the training checkpoint it came from.

A package holds what the evaluation needs: the sidecar ``MODEL.json`` names the training
configuration (``config_name``: the held-out identities, cameras and teacher resolution come from it)
and holds the decoder and scene bounds; ``MODEL.pt`` (``lp3d export --weights``) holds the encoder's
weights and the mean-triplane offset. The ONNX graph is not needed: the evaluation runs the torch
encoder, as for a checkpoint.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from lp3d.lift.model_package import ModelPackageError, load_model_package, sidecar_path
from lp3d.lift.torch_backend import read_encoder_weights
from lp3d.training.config import TRAIN_CONFIGS
from lp3d.training.student import SceneBounds, Student

__all__ = ["is_package", "package_student"]


def is_package(path: str | Path) -> bool:
    """Whether ``path`` is a model package's ``.onnx`` or ``.pt`` (its sidecar ``.json`` beside it)."""
    p = Path(path)
    return p.suffix in (".onnx", ".pt") and p.is_file() and sidecar_path(p).is_file()


def package_student(path: str | Path, device: torch.device) -> tuple[Student, dict[str, Any]]:
    """The student of the package ``path`` in eval mode, and what the evaluation reads of a checkpoint:
    ``train_config``, ``teacher`` (the default procedural one: a package does not record its teacher;
    ``--teacher`` and ``--teacher-pkl`` override it), ``path`` and ``step`` (None). Raises
    ModelPackageError naming what is missing or does not agree."""
    p = Path(path)
    pkg = load_model_package(p.with_suffix(".onnx") if p.suffix == ".pt" else p)
    cfg = TRAIN_CONFIGS.get(pkg.config_name)
    if cfg is None:
        raise ModelPackageError(
            f"{sidecar_path(p)}: config_name {pkg.config_name!r} is not a training configuration of this "
            "version; evaluate its training checkpoint instead"
        )
    weights_path = p.with_suffix(".pt")
    if not weights_path.is_file():
        raise ModelPackageError(
            f"{weights_path}: no such file; evaluating a package needs its torch weights (lp3d export "
            "--weights), or evaluate the training checkpoint"
        )
    w = read_encoder_weights(weights_path)
    # The encoder is the weights' own (a configuration's encoder may have changed since the package was
    # made); the held-out protocol is the named configuration's.
    if cfg.triplane_resolution != pkg.triplane_resolution:
        raise ModelPackageError(
            f"{sidecar_path(p)}: triplane_resolution {pkg.triplane_resolution} is not configuration "
            f"{pkg.config_name!r}'s {cfg.triplane_resolution}"
        )
    cfg = dataclasses.replace(cfg, encoder=w.config)
    scene = SceneBounds(box_warp=pkg.box_warp, ray_start=pkg.ray_start, ray_end=pkg.ray_end)
    student = Student(cfg, (pkg.w0, pkg.b0, pkg.w1, pkg.b1), scene)
    student.encoder.load_state_dict(w.state)
    if (student.plane_offset is None) != (w.offset is None):
        raise ModelPackageError(f"{weights_path}: its mean-triplane offset does not fit {pkg.config_name!r}")
    if w.offset is not None and student.plane_offset is not None:
        with torch.no_grad():
            student.plane_offset.copy_(torch.as_tensor(w.offset))
    about = {"train_config": cfg, "teacher": "procedural", "path": str(p), "step": None}
    return student.to(device).eval(), about
