"""A fuzzer of the baked-field file (:func:`lp3d.render.baked.load_baked`): a mutated file gives a
field attached to its triplane or a ValueError/OSError naming the file, never another exception, a
hang or an allocation the file did not pay for.

* byte mutations of a saved field: bit flips, size-like values written over any offset, truncation;
* entry mutations: one array replaced (another dtype, shape or value, a ``.npy`` header claiming a
  huge shape, a number out of range) and the archive zipped again with valid CRCs, so the mutation
  reaches the format's checks and the renderer's.

Seeded (``LP3D_FUZZ_SEED``, default 0) and scaled (``LP3D_FUZZ_SCALE``, default 1): a CI run is
reproducible and takes about a second.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from lp3d.render.baked import load_baked
from support.baked_files import arrays_of, baked_bytes, claiming, small_baked
from support.mutations import byte_mutant, outcomes

SEED = int(os.environ.get("LP3D_FUZZ_SEED", "0"))
SCALE = int(os.environ.get("LP3D_FUZZ_SCALE", "1"))
BYTE_MUTANTS = 150 * SCALE
ENTRY_MUTANTS = 150 * SCALE


@pytest.fixture(scope="module")
def baked(tmp_path_factory, gpu) -> tuple[object, Path]:
    return small_baked(tmp_path_factory.mktemp("baked"))


def _entry_mutant(rng: np.random.Generator, good: dict[str, np.ndarray]) -> dict[str, object]:
    arrays: dict[str, object] = dict(good)
    key = str(rng.choice(sorted(good)))
    a = good[key]
    choice = int(rng.integers(8))
    if choice == 0:
        del arrays[key]
    elif choice == 1 and a.dtype.kind != "U":  # another dtype
        arrays[key] = a.astype(rng.choice([np.float32, np.float64, np.int32, np.int64, np.uint8]))
    elif choice == 1:  # a number for a text
        arrays[key] = np.array(3)
    elif choice == 2:  # another shape
        flat = np.asarray(a).reshape(-1)
        arrays[key] = flat[: max(0, len(flat) - int(rng.integers(1, 5)))]
    elif choice == 3:  # a header claiming a huge shape over a few bytes
        dims = ", ".join(str(int(d)) for d in rng.integers(1, 2**40, size=int(rng.integers(1, 6))))
        arrays[key] = claiming(f"({dims},)", str(rng.choice(["<f2", "<i8", "<f8"])))
    elif choice == 4:  # a number out of range, fractional, huge or non-finite
        arrays[key] = np.array(rng.choice([2.5, -1, 1e300, float("nan"), 2**62, 0, 17, 1e-30]))
    elif choice == 5:  # values made non-finite or huge
        b = np.array(a, copy=True)
        if b.size and b.dtype.kind == "f":
            b.reshape(-1)[int(rng.integers(b.size))] = rng.choice([np.inf, np.nan, 6e4, -1.0])
        elif b.size and b.dtype.kind == "i":
            b.reshape(-1)[int(rng.integers(b.size))] = rng.choice([-(2**40), -2, 2**31, 2**62])
        arrays[key] = b
    elif choice == 6:  # index numbers bricks that do not exist
        index = np.array(good["index"], copy=True)
        index.reshape(-1)[int(rng.integers(index.size))] = int(rng.choice([-7, 10**6, 2**40]))
        arrays["index"] = index
    else:  # a text entry replaced
        arrays[str(rng.choice(["format", "triplane_sha256"]))] = np.array(
            str(rng.choice(["", "lp3d-baked-field-v2", "x" * 200, "\x1b[2J"]))
        )
    return arrays


def test_mutated_bytes(baked, tmp_path) -> None:
    tri, path = baked
    data = path.read_bytes()
    rng = np.random.default_rng(SEED)
    mutants = (byte_mutant(rng, data) for _ in range(BYTE_MUTANTS))
    seen = outcomes(mutants, tmp_path, lambda p: load_baked(p, tri))
    assert seen.get("ValueError", 0) > BYTE_MUTANTS // 3, seen


def test_mutated_entries(baked, tmp_path) -> None:
    tri, path = baked
    good = arrays_of(path)
    rng = np.random.default_rng(SEED + 1)
    mutants = (baked_bytes(_entry_mutant(rng, good)) for _ in range(ENTRY_MUTANTS))  # type: ignore[arg-type]
    seen = outcomes(mutants, tmp_path, lambda p: load_baked(p, tri))
    assert seen.get("ValueError", 0) > ENTRY_MUTANTS // 2 and seen.get("ok", 0) > 0, seen
