"""The teacher of a run: :func:`build_teacher` by name, the arguments a run records to rebuild it
(:data:`TEACHER_ARGS`, :func:`resolve_teacher_args`), the pretrained SR weights it may offer, and the
cache key of the synthetic dataset it makes (:func:`dataset_key`).

Imports :mod:`lp3d.training.config` only."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from lp3d.teachers import Teacher
from lp3d.teachers.procedural_decoder import DEFAULT_VERSION
from lp3d.training.config import TrainConfig
from lp3d.training.synthetic_data import DatasetKey, teacher_fingerprint

#: ``procedural`` is the embedded default (procedural teacher v2); ``procedural-v1`` is the first
#: procedural teacher, kept because the shipped ``small`` model was distilled from it (and runs made
#: before v2 recorded it as ``procedural``: resume or evaluate them with ``--teacher procedural-v1``).
TEACHERS = ("procedural", "procedural-v1", "eg3d")
PROCEDURAL_VERSIONS = {"procedural": DEFAULT_VERSION, "procedural-v1": 1}


def build_teacher(
    name: str,
    *,
    triplane_resolution: int,
    teacher_pkl: str | None = None,
    eg3d_source: str | None = None,
    conditioning: str = "gen_videos",
    device: str | torch.device = "cpu",
) -> Teacher:
    """The teacher ``name``: ``procedural`` or ``procedural-v1`` (built at the encoder's triplane
    resolution, so L_tri needs no resampling) or ``eg3d``
    (``lp3d.teachers.eg3d.EG3DTeacher.from_pickle``, imported only when asked for: loading a pickle
    executes its code; ``conditioning``: whose conditioning camera, see there)."""
    if name in PROCEDURAL_VERSIONS:
        from lp3d.teachers import ProceduralTeacher

        return ProceduralTeacher(resolution=triplane_resolution, version=PROCEDURAL_VERSIONS[name])
    if name == "eg3d":
        try:
            from lp3d.teachers import eg3d  # type: ignore[attr-defined]
        except ImportError as e:
            raise RuntimeError(
                "the EG3D teacher adapter (lp3d.teachers.eg3d) is not available in this installation "
                f"({e}); train with --teacher procedural"
            ) from None
        if teacher_pkl is None:
            raise ValueError(
                "--teacher eg3d needs --teacher-pkl PATH (an official EG3D generator pickle, e.g. "
                "ffhqrebalanced512-128.pkl) and usually --eg3d-source DIR (NVlabs/eg3d's eg3d/ folder)"
            )
        return eg3d.EG3DTeacher.from_pickle(
            teacher_pkl,
            eg3d_source=eg3d_source,
            device=device,
            conditioning=conditioning,  # type: ignore[arg-type]
        )
    raise ValueError(f"unknown teacher {name!r}; choose one of {list(TEACHERS)}")


#: The arguments of :func:`build_teacher` besides the name that a run records in its checkpoints, so
#: that ``--resume`` and ``lp3d.evaluation.evaluate`` rebuild the same teacher without being told again.
TEACHER_ARGS = ("teacher_pkl", "eg3d_source", "conditioning")


def resolve_teacher_args(ckpt: dict[str, Any] | None, **given: str | None) -> dict[str, str | None]:
    """The teacher arguments to use: those ``given`` (command-line overrides) where not None, else those
    recorded in ``ckpt`` (paths as absolute as they were recorded), else the defaults."""
    recorded = json.loads(ckpt.get("teacher_args", "{}")) if ckpt is not None else {}
    out: dict[str, str | None] = {"teacher_pkl": None, "eg3d_source": None, "conditioning": "gen_videos"}
    for k in TEACHER_ARGS:
        if given.get(k) is not None:
            out[k] = given[k]
        elif recorded.get(k) is not None:
            out[k] = recorded[k]
    return out


def recordable_teacher_args(args: dict[str, str | None]) -> dict[str, str | None]:
    """``args`` with paths made absolute, so a resume from another directory finds them."""
    return {
        k: (str(Path(v).expanduser().resolve()) if k != "conditioning" and v else v) for k, v in args.items()
    }


def teacher_superres_state(teacher: Teacher) -> dict[str, Tensor] | None:
    """Pretrained SR weights a teacher offers for the student (EG3D's ``G.superresolution``), or None."""
    fn = getattr(teacher, "superres_state_dict", None)
    if callable(fn):
        return fn()
    module = getattr(getattr(teacher, "generator", None), "superresolution", None)
    if isinstance(module, nn.Module):
        return module.state_dict()
    return None


def dataset_key(cfg: TrainConfig, teacher: Teacher, teacher_name: str) -> DatasetKey:
    """The cache key of the CPU recipe's synthetic dataset for a configuration and teacher."""
    return DatasetKey(
        teacher=teacher_name,
        teacher_fingerprint=teacher_fingerprint(teacher, cfg.train_seeds[0]),
        first_seed=cfg.train_seeds[0],
        n_identities=cfg.dataset_identities,
        image_size=cfg.image_size,
        triplane_resolution=cfg.triplane_resolution,
        depth_resolution=cfg.depth_resolution,
        depth_resolution_importance=cfg.depth_resolution_importance,
        reference_cameras=cfg.reference_cameras.to_dict(),
        camera_seed=cfg.seed,
    )
