"""What the benchmark scripts share, in one place: the timer, the encoder scenes (the shipped
encoder's triplane of a frontal render of a head, as ``lp3d demo`` lifts its teacher portrait: what
a user opens in the viewer), the baked field's scenes and views (``bench/baked.py`` and
``bench/baked_samples.py``), a random triplane, the viewer's baked settings, EG3D's own renderer set
up for comparisons, the encoder argument of the diagnostics, and the A/B runs in child processes with
their Markdown table.

Scores in dB are :func:`lp3d.render.psnr.psnr_db`, the one PSNR of lp3d: no script defines its own
(``tests/project/test_layout.py`` checks bench/ and scripts/ too). Scripts import this module as
``from harness import ...``: bench/ is on ``sys.path`` when one of them runs as a script."""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.settings import BAKED
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


# ====================================================== the baked field's scenes (baked, baked_samples)

#: Held-out identities: the training configurations draw theirs from [0, 1,000,000).
SEEDS = (1_000_003, 1_000_011)
YAWS = (-30.0, 0.0, 30.0)
PITCH = 5.0
R = 128
EPS = 1e-4
SKIP = 1e-3
#: Every skip of exact mode: the occupancy grid in both passes, early termination, empty rays.
ALL_SKIPS = {
    "occupancy_epsilon": EPS,
    "occupancy_coarse": True,
    "transmittance_threshold": SKIP,
    "empty_threshold": SKIP,
}


def scenes() -> list[tuple[str, TriplaneData]]:
    """Teacher heads and the shipped encoder's triplanes of frontal renders of them."""
    from lp3d.lift.inference import DEFAULT_MODEL
    from lp3d.teachers import ProceduralTeacher

    teacher = ProceduralTeacher(resolution=64)
    heads = [teacher.sample(s) for s in SEEDS]
    out = [(f"teacher head {s}", head) for s, head in zip(SEEDS, heads, strict=True)]
    if DEFAULT_MODEL.exists():
        encoded = encoder_outputs(heads)
        out += [(f"encoder output of {s}", tri) for s, tri in zip(SEEDS, encoded, strict=True)]
    return out


def bake(tri: object, field: tuple[int, int]) -> object:
    """Bakes the field (k, k_f) of `tri` as every row here uses it (for 24 samples and more); the
    triplane holds it, and it is returned for its size."""
    return lp3d_render.bake(
        tri, subdivisions=field[0], fine_subdivisions=field[1], occupancy_epsilon=EPS, depth_resolution=24
    )


# ============================================================================ scenes and settings


def random_triplane() -> TriplaneData:
    """A 256² random triplane with an EG3D-scaled decoder (the same one every run: seed 0)."""
    rng = np.random.default_rng(0)
    return TriplaneData(
        planes=rng.standard_normal((3, 32, 256, 256)).astype(np.float32),
        w0=(rng.standard_normal((64, 32)) / np.sqrt(32)).astype(np.float32),
        b0=(0.1 * rng.standard_normal(64)).astype(np.float32),
        w1=(rng.standard_normal((33, 64)) / 8).astype(np.float32),
        b1=(0.1 * rng.standard_normal(33)).astype(np.float32),
    )


#: The viewer's baked-frame skips (crates/viewer/src/bake.rs, `baked_settings`).
VIEWER_SKIPS = {
    "occupancy_epsilon": BAKED.occupancy_epsilon,
    "occupancy_coarse": True,
    "transmittance_threshold": 1e-3,
    "empty_threshold": 1e-3,
}
#: The viewer's fields (crates/viewer/src/bake.rs, `QUICK_FIELD`, `FINE_FIELD`): k, k_f.
QUICK_FIELD = (BAKED.baked_subdivisions, BAKED.baked_fine_subdivisions)
FINE_FIELD = (4, 16)


# ============================================================================= EG3D's own renderer


@contextlib.contextmanager
def eg3d_on_path(src: Path) -> Iterator[None]:
    """EG3D's source folder ``src`` first on ``sys.path`` for the block (checked to be one)."""
    if not (src / "training" / "volumetric_rendering" / "renderer.py").is_file():
        raise SystemExit(
            f"EG3D_SRC={src}: no training/volumetric_rendering/renderer.py there "
            "(want NVlabs/eg3d's eg3d/ folder)"
        )
    sys.path.insert(0, str(src))
    try:
        yield
    finally:
        sys.path.remove(str(src))


def eg3d_renderer(src: Path, w0: np.ndarray, b0: np.ndarray, w1: np.ndarray, b1: np.ndarray):  # noqa: ANN201
    """EG3D's (ImportanceRenderer, RaySampler, OSGDecoder) with the given effective decoder weights,
    its random draws replaced by lp3d's deterministic mode."""
    import torch

    with eg3d_on_path(src):
        from training.triplane import OSGDecoder
        from training.volumetric_rendering.ray_sampler import RaySampler
        from training.volumetric_rendering.renderer import ImportanceRenderer

    lr_mul = 1.0
    decoder = OSGDecoder(w0.shape[1], {"decoder_lr_mul": lr_mul, "decoder_output_dim": w1.shape[0] - 1})
    first, last = decoder.net[0], decoder.net[2]
    with torch.no_grad():
        first.weight.copy_(torch.from_numpy(w0) / first.weight_gain)
        first.bias.copy_(torch.from_numpy(b0) / first.bias_gain)
        last.weight.copy_(torch.from_numpy(w1) / last.weight_gain)
        last.bias.copy_(torch.from_numpy(b1) / last.bias_gain)
    renderer = ImportanceRenderer()
    # No coarse jitter: EG3D adds rand_like(depths) * delta; a zero draw leaves the linspace.
    module = sys.modules[ImportanceRenderer.__module__]
    module.torch = TorchWithoutJitter(torch)
    renderer.sample_pdf = functools.partial(renderer.sample_pdf, det=True)
    return renderer, RaySampler(), decoder


class TorchWithoutJitter:
    """``torch`` as EG3D's renderer module sees it, with ``rand_like`` returning zeros."""

    def __init__(self, torch: object) -> None:
        self._torch = torch

    def __getattr__(self, name: str) -> object:
        if name == "rand_like":
            return self._torch.zeros_like  # type: ignore[attr-defined]
        return getattr(self._torch, name)


# ============================================================================ the encoder's model


def add_model_argument(p: argparse.ArgumentParser) -> None:
    """``--model``: the encoder that error_budget.py and part_probe.py read."""
    from lp3d.lift.inference import DEFAULT_MODEL

    p.add_argument(
        "--model",
        type=Path,
        default=DEFAULT_MODEL.with_suffix(".pt"),
        help="torch weights of the encoder: a model package .pt (default: the shipped one) or a run "
        "checkpoint",
    )


def train_config_of(ckpt: dict) -> Any:
    """The training configuration named by a model package (its encoder config, a dict) or a run
    checkpoint (its training config, as JSON)."""
    from lp3d.training import TRAIN_CONFIGS

    raw = ckpt["config"]
    return TRAIN_CONFIGS[(json.loads(raw) if isinstance(raw, str) else raw)["name"]]
