"""The run's ``log.csv``, one row per training step: its columns (:data:`LOG_COLUMNS`), starting it
(a resumed run keeps the rows of the steps before it) and appending a row.

Imports nothing of lp3d."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

#: ``log.csv``'s columns; a row's other keys are not written.
LOG_COLUMNS = [
    "step",
    "stage",
    "reference",
    "seconds",
    "loss",
    "tri",
    *[f"mv_{t}" for t in ("col_raw", "col_high", "perc_raw", "perc_high", "feat", "depth", "adv", "cate")],
    *[f"ref_{t}" for t in ("col_raw", "col_high", "perc_raw", "perc_high", "feat", "depth", "adv", "cate")],
    "sr_col_high",
    "sr_perc_high",
    "ray",
    "d_loss",
    "r1",
    "lr",
]


def start_log(out_dir: Path, step: int) -> None:
    """Keep the rows of steps before ``step`` (a resumed run rewrites what came after)."""
    path = out_dir / "log.csv"
    rows: list[dict[str, str]] = []
    if path.exists() and step > 0:
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) < step]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, LOG_COLUMNS)
        w.writeheader()
        w.writerows(rows)


def append_log(out_dir: Path, row: dict[str, Any]) -> None:
    """Append one step's row (floats to 6 significant digits)."""
    with open(out_dir / "log.csv", "a", newline="") as f:
        csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore").writerow(
            {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()}
        )
