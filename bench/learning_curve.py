"""Plot a CPU-recipe run's learning curve: held-out PSNR and identity specificity against steps.

    python bench/learning_curve.py runs/small -o docs/learning-curve-small.png \
        --also runs/small-rays --also-label "with the ray loss from step 500"

Reads ``heldout.csv`` (written at every checkpoint by ``python -m lp3d.train``: novel-view PSNR of
held-out identities against their own teacher and against the others', and the difference) and
``log.csv`` (the training losses per step), and draws both panels into one PNG.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Sequence
from pathlib import Path


def _read(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _column(rows: list[dict[str, str]], key: str) -> tuple[list[int], list[float]]:
    steps, values = [], []
    for r in rows:
        if r.get(key):
            steps.append(int(r["step"]))
            values.append(float(r[key]))
    return steps, values


def plot(
    run: Path,
    out: Path,
    also: Path | None = None,
    also_label: str = "",
    *,
    title: str | None = None,
    marks: Sequence[int] = (),
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lp3d.atomic import atomic_path

    held = _read(run / "heldout.csv")
    log = _read(run / "log.csv")
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    for key, label in (("psnr_own", "vs own teacher"), ("psnr_other", "vs other identities' teachers")):
        ax.plot(*_column(held, key), marker="o", ms=3, label=label)
    ax2 = ax.twinx()
    ax2.plot(*_column(held, "specificity_db"), color="tab:green", marker="s", ms=3, label="specificity")
    if also is not None:  # a branch of the run (e.g. another phase), drawn dashed
        branch = _read(also / "heldout.csv")
        ax.plot(*_column(branch, "psnr_own"), "x--", color="tab:red", label=f"vs own teacher, {also_label}")
        ax2.plot(
            *_column(branch, "specificity_db"), "x--", color="tab:olive", label=f"specificity, {also_label}"
        )
    ax2.set_ylabel("identity specificity (dB)", color="tab:green")
    ax.set_xlabel("step")
    ax.set_ylabel("held-out novel-view PSNR (dB)")
    ax.set_title(f"{title or run.name}: {len(held)} evaluations on held-out identities", fontsize=10)
    for step in marks:  # e.g. where a resumed run's schedule was lengthened
        for axis in (ax, bx):
            axis.axvline(step, color="grey", lw=0.8, ls=":")
    lines = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    labels = ax.get_legend_handles_labels()[1] + ax2.get_legend_handles_labels()[1]
    ax.legend(lines, labels, loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    for key, label in (("tri", "normalised L_tri"), ("ray", "random-ray RGB L1")):
        steps, values = _column(log, key)
        if values:
            # A running mean over 25 steps: single batches are noisy.
            k = 25
            smooth = [
                sum(values[max(0, i - k + 1) : i + 1]) / len(values[max(0, i - k + 1) : i + 1])
                for i in range(len(values))
            ]
            bx.plot(steps, smooth, label=label)
    bx.set_yscale("log")
    bx.set_xlabel("step")
    bx.set_ylabel("training loss (running mean of 25 steps)")
    bx.legend(fontsize=8)
    bx.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, help="a run directory of python -m lp3d.train (CPU recipe)")
    p.add_argument("-o", "--out", type=Path, required=True, help="PNG to write")
    p.add_argument("--also", type=Path, default=None, help="a branch run directory to overlay (dashed)")
    p.add_argument("--also-label", default="branch", help="legend label of --also")
    p.add_argument("--title", default=None, help="the left plot's title (default: the run folder's name)")
    p.add_argument("--mark", type=int, nargs="*", default=[], help="steps to mark with a dotted line")
    args = p.parse_args(argv)
    for name in ("heldout.csv", "log.csv"):
        if not (args.run / name).is_file():
            print(
                f"error: {args.run / name} not found (is this a CPU-recipe run directory?)", file=sys.stderr
            )
            return 1
    print(plot(args.run, args.out, args.also, args.also_label, title=args.title, marks=args.mark))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
