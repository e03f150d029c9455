"""Training checkpoints: their format (:data:`CHECKPOINT_FORMAT`), writing them
(:func:`write_checkpoint`, atomic, keeping the last few), reading them (:func:`load_checkpoint`, on
every rank :func:`load_shared_checkpoint`, :func:`student_from_checkpoint`), and the RNG states they
carry so that a resume is exact (:func:`rng_states`, :func:`restore_rng_states`, :func:`rank_seed`).

Imports :mod:`lp3d.training.config`, :mod:`lp3d.training.student`, :mod:`lp3d.training.run_dir`
and :mod:`lp3d.training.distributed`."""

from __future__ import annotations

import json
import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lp3d.atomic import atomic_path
from lp3d.render.npz_reader import read_torch_file
from lp3d.training import distributed
from lp3d.training.config import TrainConfig
from lp3d.training.run_dir import checkpoint_path, checkpoints, newest_readable
from lp3d.training.student import SceneBounds, Student

#: Identifies lp3d training checkpoints; bumped when the layout changes.
CHECKPOINT_FORMAT = "lp3d-train-checkpoint-v1"


#: What a weights-only checkpoint keeps (:func:`weights_only_checkpoint`): enough for
#: :func:`load_checkpoint` and :func:`student_from_checkpoint`, not for ``--resume``.
WEIGHTS_ONLY_KEYS = ("format", "config", "teacher", "teacher_args", "scene", "step", "student")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used here (another configuration, another format, a bad file)."""


def write_checkpoint(state: dict[str, Any], run_dir: Path, keep: int) -> Path:
    """Write ``state`` (its ``step``) as ``run_dir/checkpoints/step-NNNNNN.pt`` atomically (never
    half-written) and delete all but the last ``keep`` checkpoints; returns its path."""
    path = checkpoint_path(run_dir, int(state["step"]))
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    for _, p in checkpoints(run_dir)[:-keep]:
        p.unlink(missing_ok=True)
    return path


def weights_only_checkpoint(ckpt: dict[str, Any]) -> dict[str, Any]:
    """The parts of a loaded checkpoint that rebuild its student (:data:`WEIGHTS_ONLY_KEYS`), tensors
    on the CPU, marked ``weights_only``: what ``lp3d eval``, ``lp3d export`` and ``--init-from`` read,
    a third of the file without the optimiser's state; ``--resume`` refuses it
    (:func:`lp3d.training.resume.refuse_weights_only`)."""
    slim = {k: ckpt[k] for k in WEIGHTS_ONLY_KEYS if k in ckpt}
    slim["student"] = {k: v.detach().to("cpu", copy=True).contiguous() for k, v in ckpt["student"].items()}
    slim["weights_only"] = True
    return slim


def load_checkpoint(
    path: str | os.PathLike[str], *, map_location: str | torch.device = "cpu"
) -> dict[str, Any]:
    """Read a training checkpoint (a run directory means its latest); never unpickles code.

    Returns the raw dict with ``config`` parsed into a :class:`TrainConfig` under ``"train_config"``.
    For a run directory, an unreadable newest checkpoint (a kill or a full disk mid-copy) is skipped
    with a warning in favour of the newest readable one.

    Raises:
        CheckpointError: not a file, not an lp3d checkpoint, another format version.
    """
    p = Path(path)
    if p.is_dir():
        return newest_readable(p, lambda f: load_checkpoint(f, map_location=map_location), CheckpointError)
    if not p.exists():
        raise CheckpointError(f"checkpoint {str(p)!r}: no such file")
    try:
        ckpt = read_torch_file(p, "a training checkpoint", map_location)
    except (OSError, ValueError) as e:
        raise CheckpointError(f"checkpoint {e}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        got = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(
            f"{str(p)!r} is not an lp3d training checkpoint of format {CHECKPOINT_FORMAT!r} (got {got!r})"
        )
    _check_entries(ckpt, str(p))
    try:
        ckpt["train_config"] = TrainConfig.from_json(ckpt["config"])
    except (ValueError, TypeError, KeyError) as e:
        raise CheckpointError(f"{str(p)!r}: its configuration cannot be read by this version: {e}") from None
    ckpt["path"] = str(p)
    return ckpt


#: The decoder's entries every student holds (``student_from_checkpoint`` reads them first).
_DECODER_KEYS = tuple(f"decoder.{n}" for n in ("w0", "b0", "w1", "b1"))


def _check_entries(ckpt: dict[Any, Any], where: str) -> None:
    """The entries every reader of a checkpoint uses (:data:`WEIGHTS_ONLY_KEYS`), with their types,
    so that a file someone edited or cut short is a :class:`CheckpointError` naming the entry here,
    not a ``KeyError`` or ``AttributeError`` deep in evaluation or export."""

    def bad(key: str, what: str) -> CheckpointError:
        got = ckpt.get(key)
        shown = type(got).__name__ if key in ckpt else "nothing"
        return CheckpointError(f"checkpoint {where!r}: entry {key!r} must be {what}, got {shown}")

    for key in ("config", "teacher", "scene"):
        if not isinstance(ckpt.get(key), str):
            raise bad(key, "a string")
    if "teacher_args" in ckpt and not isinstance(ckpt["teacher_args"], str):
        raise bad("teacher_args", "a JSON string")
    step = ckpt.get("step")
    if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step < 2**62:
        raise bad("step", "a step number (a non-negative int)")
    try:
        scene = json.loads(ckpt["scene"])
    except ValueError:
        scene = None
    if not isinstance(scene, dict):
        raise bad("scene", "the JSON of the scene bounds")
    student = ckpt.get("student")
    if not isinstance(student, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in student.items()
    ):
        raise bad("student", "a state dict (names to tensors)")
    missing = [k for k in _DECODER_KEYS if k not in student]
    if missing:
        raise CheckpointError(f"checkpoint {where!r}: its student has no {', '.join(missing)}")


def load_shared_checkpoint(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> dict[str, Any]:
    """:func:`load_checkpoint` on every rank of the same file: under torchrun rank 0 picks it (a run
    directory means its newest readable checkpoint) and tells the others which."""
    if distributed.is_main():
        ckpt = load_checkpoint(path, map_location=device)
        distributed.broadcast_object(ckpt["path"])
        return ckpt
    return load_checkpoint(distributed.broadcast_object(""), map_location=device)


def rank_seed(seed: int, rank: int, step: int) -> int:
    """The torch seed of a rank other than 0 (its own dropout masks), from the run's seed, the rank and
    the step it starts its streams at; rank 0 keeps the single-process streams."""
    return int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0])


def student_from_checkpoint(ckpt: dict[str, Any], device: torch.device | str = "cpu") -> Student:
    """Rebuild the student of a checkpoint (from :func:`load_checkpoint`) in eval mode."""
    cfg: TrainConfig = ckpt["train_config"]
    where = ckpt.get("path", "?")
    try:
        scene = SceneBounds(**json.loads(ckpt["scene"]))
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {where!r}: entry 'scene' holds no scene bounds: {e}") from None
    if (problem := scene.problem()) is not None:
        raise CheckpointError(f"checkpoint {where!r}: entry 'scene': {problem[0]}: {problem[1]}")
    dec = ckpt["student"]
    decoder = tuple(dec[key].detach().cpu().float().numpy() for key in _DECODER_KEYS)
    try:
        student = Student(cfg, decoder, scene)  # type: ignore[arg-type]
        student.load_state_dict(ckpt["student"])
    except (RuntimeError, ValueError, TypeError) as e:
        raise CheckpointError(f"checkpoint weights do not fit configuration {cfg.name!r}: {e}") from None
    return student.to(device).eval()


def rng_states() -> dict[str, Any]:
    """This process's Python, NumPy (global), torch and CUDA RNG states, as a checkpoint stores them."""
    py = random.getstate()
    np_state = np.random.get_state()  # noqa: NPY002  (the global state other code may use)
    out: dict[str, Any] = {
        "python": json.dumps([py[0], list(py[1]), py[2]]),
        "numpy": json.dumps(
            [
                np_state[0],
                np.asarray(np_state[1]).tolist(),
                int(np_state[2]),
                int(np_state[3]),
                float(np_state[4]),
            ]
        ),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def restore_rng_states(states: dict[str, Any]) -> None:
    """Set this process's RNG states to ``states`` (from :func:`rng_states`)."""
    v, s, g = json.loads(states["python"])
    random.setstate((v, tuple(s), g))
    n = json.loads(states["numpy"])
    legacy = (n[0], np.asarray(n[1], dtype=np.uint32), n[2], n[3], n[4])
    np.random.set_state(legacy)  # noqa: NPY002
    torch.set_rng_state(states["torch"].cpu())
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([t.cpu() for t in states["cuda"]])
