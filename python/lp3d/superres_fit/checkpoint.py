"""A super-resolution fit's checkpoint (``superres-fit.pt``, format :data:`FIT_FORMAT`): a plain dict
of tensors and JSON strings, written atomically
(:func:`fit_checkpoint`, :func:`save_fit_checkpoint`) and read back
without unpickling code (:func:`load_fit`).

Imports lp3d.atomic, lp3d.nets.superres and lp3d.superres_fit.config.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from lp3d.atomic import atomic_path
from lp3d.nets.superres import SuperresConfig, SuperResolution
from lp3d.render.npz_reader import read_torch_file
from lp3d.superres_fit.config import FitConfig, FitError

__all__ = ["CHECKPOINT_NAME", "FIT_FORMAT", "LoadedFit", "load_fit"]

#: The ``format`` of a fit checkpoint.
FIT_FORMAT = "lp3d-superres-fit-v1"
CHECKPOINT_NAME = "superres-fit.pt"


def fit_checkpoint(
    sr: SuperResolution,
    opt: torch.optim.Optimizer,
    cfg: FitConfig,
    step: int,
    model: dict[str, Any],
    pairs: dict[str, str],
    report: dict[str, Any] | None,
) -> dict[str, Any]:
    return {
        "format": FIT_FORMAT,
        "fit_config": json.dumps(cfg.to_dict(), sort_keys=True),
        "superres_config": json.dumps(sr.config.to_dict(), sort_keys=True),
        "superres": {k: v.detach().cpu().clone() for k, v in sr.state_dict().items()},
        "optimizer": opt.state_dict(),
        "step": step,
        "model": json.dumps(model, sort_keys=True),
        "pairs": json.dumps(pairs, sort_keys=True),
        "report": json.dumps(report, sort_keys=True),
    }


def save_fit_checkpoint(ckpt: dict[str, Any], path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(ckpt, tmp)


@dataclass
class LoadedFit:
    """A fit checkpoint read back (:func:`load_fit`)."""

    path: Path
    config: FitConfig
    superres: SuperResolution
    step: int
    model: dict[str, Any]
    report: dict[str, Any] | None
    raw: dict[str, Any]

    @property
    def finished(self) -> bool:
        return self.step >= self.config.steps and self.report is not None


def load_fit(path: str | os.PathLike[str]) -> LoadedFit:
    """Read a fit checkpoint (a folder means its ``superres-fit.pt``); never unpickles code.
    Raises :class:`FitError` naming the file and what is wrong."""
    p = Path(path)
    if p.is_dir():
        p = p / CHECKPOINT_NAME
    if not p.exists():
        raise FitError(f"{p}: no such super-resolution fit checkpoint")
    try:
        ckpt = read_torch_file(p, "a super-resolution fit checkpoint")
    except (OSError, ValueError) as e:
        raise FitError(str(e)) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FIT_FORMAT:
        got = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise FitError(f"{p}: not a super-resolution fit checkpoint of format {FIT_FORMAT!r} (got {got!r})")
    try:
        cfg = FitConfig.from_dict(json.loads(ckpt["fit_config"]))
        sr_cfg = SuperresConfig.from_dict(json.loads(ckpt["superres_config"]))
        sr = SuperResolution(sr_cfg)
        sr.load_state_dict(ckpt["superres"], strict=True)
        step = int(ckpt["step"])
        model = json.loads(ckpt["model"])
        report = json.loads(ckpt["report"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise FitError(
            f"{p}: malformed fit checkpoint ({type(e).__name__}: {str(e).splitlines()[0]})"
        ) from None
    return LoadedFit(p, cfg, sr.eval(), step, model, report, ckpt)
