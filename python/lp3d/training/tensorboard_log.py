"""TensorBoard event files for a training run, beside ``log.csv``: ``RUN/tensorboard/``.

Written when the ``tensorboard`` package is installed (``pip install ".[train]"`` brings it), silently
absent otherwise: ``log.csv`` and ``heldout.csv`` stay the run's record, this is for watching it.
``tensorboard --logdir runs/`` shows every run. Tags:

* ``loss/<term>``: each loss term of ``log.csv`` (``loss/total`` is their weighted sum);
* ``lr``: the student's learning rate; ``time/seconds_per_step``;
* ``heldout/<metric>``: the CPU recipe's learning curve (``heldout.csv``);
* ``samples``: the sample sheet of ``samples/step-NNNNNN.png``.

The x axis is the number of steps done: ``log.csv``'s row ``step`` (the index of the step) is drawn at
``step + 1``, so a step's losses and the checkpoint written after it share a point. A resumed run
purges the events after the step it continues from, as ``log.csv`` drops its rows.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["TensorBoardLog", "tensorboard_available"]

#: ``log.csv`` columns that are not loss terms.
_NOT_LOSSES = frozenset({"step", "stage", "reference", "seconds", "lr"})


def tensorboard_available() -> bool:
    try:
        import tensorboard  # noqa: F401
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError:
        return False
    return True


class TensorBoardLog:
    """One run's event writer; every method is a no-op when TensorBoard is not installed."""

    def __init__(self, run_dir: Path, *, start_step: int) -> None:
        self.dir = Path(run_dir) / "tensorboard"
        self._writer: Any = None
        if tensorboard_available():
            from torch.utils.tensorboard import SummaryWriter

            # purge_step: events after start_step, left by the abandoned part of a resumed run, are hidden.
            self._writer = SummaryWriter(
                log_dir=str(self.dir), purge_step=start_step + 1 if start_step else None
            )

    @property
    def active(self) -> bool:
        return self._writer is not None

    def step_row(self, row: dict[str, Any]) -> None:
        """One ``log.csv`` row, drawn at ``row["step"] + 1`` (steps done)."""
        if self._writer is None:
            return
        step = int(row["step"]) + 1
        for key, value in row.items():
            if key in _NOT_LOSSES or not isinstance(value, (int, float)) or not math.isfinite(value):
                continue
            self._writer.add_scalar("loss/total" if key == "loss" else f"loss/{key}", value, step)
        if isinstance(row.get("lr"), (int, float)):
            self._writer.add_scalar("lr", row["lr"], step)
        if isinstance(row.get("seconds"), (int, float)):
            self._writer.add_scalar("time/seconds_per_step", row["seconds"], step)

    def heldout(self, step: int, metrics: dict[str, float]) -> None:
        if self._writer is None:
            return
        for key, value in metrics.items():
            self._writer.add_scalar(f"heldout/{key}", value, step)

    def samples(self, step: int, image: np.ndarray) -> None:
        """An (H, W, 3) uint8 sample sheet."""
        if self._writer is not None:
            self._writer.add_image("samples", image, step, dataformats="HWC")

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
