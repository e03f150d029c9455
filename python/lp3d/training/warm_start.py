"""Start a new run's encoder from trained weights (``--init-from``), where the new configuration
grows the old network instead of replacing it.

Why: a change to the encoder (a colour grid in the codes, more basis components) would otherwise be
judged only after a retrain of hours; started from the shipped weights, with what was added starting
at zero, the new network begins exactly where the old one ended and a short run shows what the
change adds. The same short run from the old configuration is the fair comparison.

The source is a model package (``lp3d/lift/models/small.pt``) or a run checkpoint, read and checked by
:func:`lp3d.lift.torch_backend.read_encoder_weights` (``weights_only=True``: no pickle execution).
Each tensor of the student's encoder is

* copied when the source has it with the same shape;
* copied into its leading block when it is one the configuration may grow (:data:`GROWABLE`) and
  the new one is larger along that dimension, with the rest zero for a code layer's new inputs (so
  the output is unchanged) or left at its fresh start for new basis components (their coefficients'
  rows are zero, so they add nothing yet);
* an error naming the tensor otherwise (a source from another network).

Imports lp3d.lift.torch_backend and lp3d.training.student.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from lp3d.lift.torch_backend import ModelPackageError, read_encoder_weights
from lp3d.training.student import Student

#: The tensors a configuration may grow, and along which dimension: the code layers' inputs (the
#: colour grid, ``colour_pool``) and the basis's components (``basis_components``).
GROWABLE = {
    "basis.coefficients.1.weight": 1,
    "generator.code.1.weight": 1,
    "basis.coefficients.3.weight": 0,
    "basis.coefficients.3.bias": 0,
    "basis.components": 0,
}
#: Grown tensors whose new part keeps its fresh start (new components; their coefficients are zero).
_KEEP_FRESH = ("basis.components",)


class WarmStartError(ValueError):
    """The weights given to ``--init-from`` cannot start this run's encoder."""


@dataclass(frozen=True)
class WarmStart:
    """What a warm start did: the source, and how many tensors were copied whole or in part."""

    source: Path
    sha256: str
    copied: int
    grown: tuple[str, ...]

    def to_json(self) -> str:
        return json.dumps(
            {
                "source": str(self.source),
                "sha256": self.sha256,
                "copied": self.copied,
                "grown": list(self.grown),
            },
            indent=2,
        )

    def describe(self) -> str:
        grown = f"; grown from a smaller tensor: {', '.join(self.grown)}" if self.grown else ""
        return f"encoder started from {self.source}: {self.copied} tensors copied{grown}"


def _source_tensors(path: Path) -> tuple[dict[str, Tensor], Tensor | None, Path, str]:
    """(encoder state, plane offset or None, the file read, its SHA-256) of a model package or a run
    checkpoint, read and checked as ``lp3d encode --backend torch`` reads it."""
    try:
        weights = read_encoder_weights(path)
    except ModelPackageError as e:
        raise WarmStartError(f"--init-from: {e}") from None
    digest = hashlib.sha256(weights.path.read_bytes()).hexdigest()  # for warm_start.json
    return weights.state, weights.offset, weights.path, digest


def _leading_block(name: str, new: Tensor, old: Tensor) -> tuple[slice, ...] | None:
    """The slices of ``new`` that ``old`` fills, when ``name`` may grow (:data:`GROWABLE`) and ``old``
    is smaller along that dimension only."""
    dim = GROWABLE.get(name)
    if dim is None or new.ndim != old.ndim or old.shape[dim] > new.shape[dim]:
        return None
    if any(o != n for d, (o, n) in enumerate(zip(old.shape, new.shape, strict=True)) if d != dim):
        return None
    return tuple(slice(0, o) for o in old.shape)


@torch.no_grad()
def warm_start(student: Student, path: str | os.PathLike[str]) -> WarmStart:
    """Copy the weights at ``path`` into ``student``'s encoder (and plane offset), growing where the
    new configuration is larger (module docstring). Raises :class:`WarmStartError` naming the first
    tensor that does not fit, before changing anything."""
    source = Path(path)
    encoder, offset, source, digest = _source_tensors(source)  # a run folder: its newest checkpoint
    target = student.encoder.state_dict()
    missing = sorted(set(target) - set(encoder))
    extra = sorted(set(encoder) - set(target))
    if missing or extra:
        raise WarmStartError(
            f"--init-from {source}: another network (missing {missing[:3]}, unexpected {extra[:3]})"
        )
    plans: list[tuple[str, tuple[slice, ...] | None]] = []
    for name, new in target.items():
        old = encoder[name]
        if old.shape == new.shape:
            plans.append((name, None))
            continue
        block = _leading_block(name, new, old)
        if block is None:
            raise WarmStartError(
                f"--init-from {source}: {name} has shape {tuple(old.shape)}, this run's "
                f"{tuple(new.shape)}; only the code layers' inputs and the basis's components may grow"
            )
        plans.append((name, block))
    if offset is not None and student.plane_offset is not None and offset.shape != student.plane_offset.shape:
        raise WarmStartError(
            f"--init-from {source}: plane_offset has shape {tuple(offset.shape)}, this run's "
            f"{tuple(student.plane_offset.shape)}"
        )
    grown = []
    for name, block in plans:
        new, old = target[name], encoder[name].to(target[name].dtype)
        if block is None:
            new.copy_(old)
            continue
        if name not in _KEEP_FRESH:
            new.zero_()  # new inputs (columns) and new outputs (rows, bias) start at zero
        new[block] = old
        grown.append(name)
    student.encoder.load_state_dict(target)
    if offset is not None and student.plane_offset is not None:
        student.plane_offset.copy_(offset)
    return WarmStart(source=source.resolve(), sha256=digest, copied=len(plans), grown=tuple(grown))
