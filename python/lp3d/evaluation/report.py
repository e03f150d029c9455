"""What an evaluation writes: the comparison figure, report.json and the summary table printed by
``lp3d eval`` (:mod:`lp3d.evaluation.evaluate` makes the report).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.atomic import atomic_write_text
from lp3d.images import save_png, tile


def comparison_figure(
    rows: list[list[list[np.ndarray]]],
    labels: Sequence[str],
    *,
    notes: Sequence[str] | None = None,
    title: str | None = None,
    max_tile: int = 256,
) -> np.ndarray:
    """One image: per identity, one row per method (``labels``), with the label at the left.

    ``notes``: one line per identity, drawn under its first label (e.g. the input yaw). ``title``: a
    line above the grid. Tiles larger than ``max_tile`` pixels are downscaled to keep the image small.
    """
    from PIL import Image, ImageDraw

    flat = [img for identity in rows for row in identity for img in row]
    if flat[0].shape[0] > max_tile:
        size = (max_tile * flat[0].shape[1] // flat[0].shape[0], max_tile)
        flat = [np.asarray(Image.fromarray(img).resize(size, Image.Resampling.LANCZOS)) for img in flat]
    columns = len(rows[0][0])
    grid = tile(flat, columns)
    margin = 80
    top = 16 if title else 0
    canvas = Image.new("RGB", (grid.shape[1] + margin, grid.shape[0] + top), (24, 24, 24))
    canvas.paste(Image.fromarray(grid), (margin, top))
    draw = ImageDraw.Draw(canvas)
    if title:
        draw.text((4, 2), title, fill=(230, 230, 230))
    h = flat[0].shape[0]
    r = 0
    for k, identity in enumerate(rows):
        for i, _ in enumerate(identity):
            y = top + 2 + r * (h + 2) + h // 2 - 6
            draw.text((4, y), labels[i], fill=(230, 230, 230))
            if i == 0 and notes is not None:
                draw.text((4, y + 12), notes[k], fill=(160, 160, 160))
            r += 1
    return np.asarray(canvas)


def figure_labels(report: dict[str, Any]) -> list[str]:
    """The row labels of :func:`evaluate`'s figure rows for ``report``."""
    optional = [m for m in ("refined", "baseline") if m in report]
    return ["teacher", "student", *optional, "ceiling"]


def write_outputs(
    report: dict[str, Any], rows: list[list[list[np.ndarray]]], out_dir: str | os.PathLike[str]
) -> tuple[Path, Path]:
    """Write ``report.json`` and ``comparison.png`` into ``out_dir``; returns their paths."""
    out_dir = Path(out_dir)
    report_path = out_dir / "report.json"
    atomic_write_text(report_path, json.dumps(report, indent=2) + "\n")
    shown = len(rows)
    total = len(report["identity_seeds"])
    notes = [f"yaw {r['input_yaw_deg']:+.0f}" for r in report["per_identity"][:shown]]
    title = (
        f"first {shown} of {total} held-out identities" if shown < total else f"{total} held-out identities"
    ) + "; columns: input, then novel views"
    png = save_png(
        out_dir / "comparison.png", comparison_figure(rows, figure_labels(report), notes=notes, title=title)
    )
    return report_path, png


def summary_table(report: dict[str, Any]) -> str:
    """The printed summary: method | input PSNR | novel PSNR own | vs other identities | specificity |
    SSIM."""

    def db(v: float | None, sign: bool = False) -> str:
        return "n/a" if v is None else (f"{v:+.2f} dB" if sign else f"{v:.2f} dB")

    def num(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f}"

    head = ("method", "input PSNR", "novel PSNR own", "vs other identities", "specificity", "SSIM")
    lines = [head]
    for method in ("student", "flip_averaged", "refined", "refined_photo", "baseline", "floor", "ceiling"):
        s = report.get(method)
        if s is None:
            continue
        lines.append(
            (
                method,
                db(s.get("input_psnr")),
                db(s.get("novel_psnr")),
                db(s.get("novel_psnr_other")),
                db(s.get("identity_specificity_db"), sign=True),
                num(s.get("novel_ssim")),
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    out = []
    for j, line in enumerate(lines):
        cells = [line[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(line[1:], widths[1:], strict=True)]
        out.append(" | ".join(cells))
        if j == 0:
            out.append("-+-".join("-" * w for w in widths))
    return "\n".join(out)
