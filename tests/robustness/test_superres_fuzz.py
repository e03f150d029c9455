"""A fuzzer of the super-resolution weights file (``MODEL.superres.npz``, read by the renderer's
``SuperresWeights::load`` through ``lp3d_render.SuperRes.load``): a mutated file gives a network or a
ValueError/OSError naming the file, never another exception, a crash, a hang or an allocation the
file did not pay for.

* byte mutations of the shipped model's file: bit flips, size-like values written over any offset,
  truncation;
* entry mutations: one array replaced (another dtype or shape, a ``.npy`` header claiming a huge
  shape, non-finite values, a number out of range) or removed, and the archive zipped again with
  valid CRCs, so the mutation reaches the format's checks.

Seeded (``LP3D_FUZZ_SEED``, default 0) and scaled (``LP3D_FUZZ_SCALE``, default 1): a CI run is
reproducible and takes a few seconds.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import lp3d_render
from lp3d.lift.inference import DEFAULT_MODEL
from lp3d.lift.model_package import load_model_package
from support.baked_files import arrays_of, baked_bytes, claiming
from support.mutations import byte_mutant, outcomes

SEED = int(os.environ.get("LP3D_FUZZ_SEED", "0"))
SCALE = int(os.environ.get("LP3D_FUZZ_SCALE", "1"))
MUTANTS = 60 * SCALE


@pytest.fixture(scope="module")
def weights() -> Path:
    entry = load_model_package(DEFAULT_MODEL).superres
    assert entry is not None, "the shipped model has no super-resolution network"
    return entry.weights_path


def _entry_mutant(rng: np.random.Generator, good: dict[str, np.ndarray]) -> dict[str, object]:
    arrays: dict[str, object] = dict(good)
    key = str(rng.choice(sorted(good)))
    a = good[key]
    choice = int(rng.integers(6))
    if choice == 0:
        del arrays[key]
    elif choice == 1:  # another dtype
        arrays[key] = a.astype(rng.choice([np.float16, np.float64, np.int32, np.int64, np.uint8]))
    elif choice == 2:  # another shape
        flat = np.asarray(a).reshape(-1)
        arrays[key] = flat[: max(0, len(flat) - int(rng.integers(0, 5)))]
    elif choice == 3:  # a header claiming a huge shape over a few bytes
        dims = ", ".join(str(int(d)) for d in rng.integers(1, 2**40, size=int(rng.integers(1, 6))))
        arrays[key] = claiming(f"({dims},)", str(rng.choice(["<f4", "<i8", "<f8"])))
    elif choice == 4:  # a number out of range or of another kind
        arrays[key] = np.array(rng.choice([2.5, -1, 1e300, float("nan"), 2**62, 0, 4096]))
    else:  # a value made non-finite or huge
        b = np.array(a, copy=True)
        if b.size and b.dtype.kind == "f":
            b.reshape(-1)[int(rng.integers(b.size))] = rng.choice([np.inf, np.nan, 3e38])
        arrays[key] = b
    return arrays


def test_mutated_bytes(gpu, weights, tmp_path) -> None:
    data = weights.read_bytes()
    rng = np.random.default_rng(SEED)
    mutants = (byte_mutant(rng, data) for _ in range(MUTANTS))
    seen = outcomes(mutants, tmp_path, lp3d_render.SuperRes.load)
    print("byte mutants:", seen)
    assert seen.get("ValueError", 0) > MUTANTS // 3, seen


def test_mutated_entries(gpu, weights, tmp_path) -> None:
    good = arrays_of(weights)
    rng = np.random.default_rng(SEED + 1)
    mutants = (baked_bytes(_entry_mutant(rng, good)) for _ in range(MUTANTS))  # type: ignore[arg-type]
    seen = outcomes(mutants, tmp_path, lp3d_render.SuperRes.load)
    print("entry mutants:", seen)
    # Flipped or huge weights that stay finite load (the network then overflows at apply time,
    # which `apply` reports); everything else is refused.
    assert seen.get("ValueError", 0) > MUTANTS // 2, seen
