"""What the benchmark scripts share, in one place: the timer, the encoder scenes (the shipped
encoder's triplane of a frontal render of a head, as ``lp3d demo`` lifts its teacher portrait: what
a user opens in the viewer), and the A/B runs in child processes with their Markdown table.

Scores in dB are :func:`lp3d.render.psnr.psnr_db`, the one PSNR of lp3d: no script defines its own
(``tests/project/test_layout.py`` checks bench/ and scripts/ too). Scripts import this module as
``from harness import ...``: bench/ is on ``sys.path`` when one of them runs as a script."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.triplane import TriplaneData

T = TypeVar("T")


# ============================================================================================== timer


def timed(fn: Callable[[], T], repeats: int) -> tuple[float, T]:
    """The median wall time of ``repeats`` calls of ``fn`` in milliseconds, and the last call's result
    (the median: one slow spell of a shared machine does not move it)."""
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), out  # type: ignore[return-value]


# ===================================================================================== encoder scenes


def encoder_outputs(heads: Iterable[TriplaneData]) -> Iterator[TriplaneData]:
    """For each head, the shipped encoder's triplane of its frontal render at the encoder's input
    size (the encoder is loaded once, on the first head)."""
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder

    enc = None
    for head in heads:
        enc = enc or load_encoder(DEFAULT_MODEL)
        size = enc.package.image_size
        image = lp3d_render.render(head.to_native(), look_at_camera(), resolution=size)["rgb"]
        yield enc.package.triplane(enc.run(image[None].astype(np.float32))[0])


def encoder_output(head: TriplaneData) -> TriplaneData:
    """`encoder_outputs` of one head."""
    return next(encoder_outputs([head]))


def saved_encoder_output(seed: int, folder: Path) -> TriplaneData:
    """`encoder_output` of procedural teacher head `seed`, encoded once and kept in `folder` as
    ``encoder-<seed>.npz`` (delete it to encode again with another model)."""
    from lp3d.render.triplane_io import load_triplane, save_triplane
    from lp3d.teachers import ProceduralTeacher

    path = folder / f"encoder-{seed}.npz"
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        print(f"encoding head {seed}", file=sys.stderr, flush=True)
        save_triplane(path, encoder_output(ProceduralTeacher().sample(seed)))
    return load_triplane(path)


# ============================================================================ A/B runs in children
# The A/B scripts (``drag_frames.py``, ``full_walk.py``) run their timing in fresh child processes
# that differ only in their environment (a build on ``PYTHONPATH``, a setting like
# ``LP3D_FULL_WALK``), alternated so that a slow spell of the machine hits every side.


def child_rows(script: str, child_args: list[str], env: dict[str, str]) -> list[dict]:
    """Runs ``script --child child_args`` under ``env``; the JSON objects it printed, one per line."""
    cmd = [sys.executable, script, "--child", *child_args]
    done = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True, check=True)
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def emit_table(lines: list[str], out: Path | None) -> None:
    """Prints the table and, with ``out``, writes it there too."""
    table = "\n".join(lines)
    print("\n" + table)
    if out:
        out.write_text(table + "\n")
