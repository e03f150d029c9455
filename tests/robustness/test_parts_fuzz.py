"""A fuzzer of the checkpoint-part manifest (``scripts/checkpoint_parts.py join``): a mutated
manifest joins to the checkpoint it lists or is a ``PartsError`` (one line, naming the manifest or the
part), never another exception, a hang or a read larger than the manifest's own cap.

* structure edits: a field dropped, retyped (huge, negative, fractional, boolean numbers; lists,
  strings, nesting), parts dropped, repeated or renamed (paths, hidden names, long names);
* byte mutations of the manifest's JSON: bit flips, truncation, splices, arrays nested up to 200,000
  deep.

Seeded (``LP3D_FUZZ_SEED``, default 0) and scaled (``LP3D_FUZZ_SCALE``, default 1): ~2 s in CI.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import torch

from support.checkpoints import parts_module, tiny_state

SEED = int(os.environ.get("LP3D_FUZZ_SEED", "0"))
SCALE = int(os.environ.get("LP3D_FUZZ_SCALE", "1"))
STRUCTURE_MUTANTS = 120 * SCALE
BYTE_MUTANTS = 120 * SCALE
ODD_VALUES: list[Any] = [
    None, True, -1, 0, 1.5, 2**63, 10**400, "", "x" * 300, [], {}, [[[]]], "../step-000007.part00",
    ".hidden", "step-000007.part00", "/dev/zero", float("nan"),
]  # fmt: skip


@pytest.fixture(scope="module")
def parts() -> ModuleType:
    return parts_module()


@pytest.fixture(scope="module")
def manifest(parts, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("parts")
    ckpt = folder / "run" / "step-000007.pt"
    ckpt.parent.mkdir()
    torch.save(tiny_state(), ckpt)
    return parts.split(ckpt, folder / "out", 4 << 20)


def _outcome(parts: ModuleType, manifest: Path, dest: Path) -> str:
    try:
        parts.join(manifest, dest)
    except parts.PartsError as e:
        text = str(e)
        assert "\n" not in text and len(text) < 2000, text
        return "refused"
    return "joined"


def _edit(rng: np.random.Generator, listed: dict[str, Any]) -> dict[str, Any]:
    out = json.loads(json.dumps(listed))
    where = out if rng.random() < 0.4 else out["parts"][int(rng.integers(len(out["parts"])))]
    choice = int(rng.integers(5))
    keys = sorted(where)
    if choice == 0 and keys:
        del where[str(rng.choice(keys))]
    elif choice in (1, 2) and keys:
        where[str(rng.choice(keys))] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    elif choice == 3:
        p = out["parts"]
        op = int(rng.integers(3))
        if op == 0:
            p.pop(int(rng.integers(len(p))))
        elif op == 1:
            p.append(p[int(rng.integers(len(p)))])
        else:
            out["parts"] = p * 300
    else:
        out[str(rng.choice(["extra", "parts", "format"]))] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    return out


def test_structure_mutants(parts, manifest, tmp_path) -> None:
    listed = json.loads(manifest.read_text())
    rng = np.random.default_rng(SEED)
    seen: dict[str, int] = {}
    for i in range(STRUCTURE_MUTANTS):
        mutant = manifest.parent / f"mutant-{i}.parts.json"
        mutant.write_text(json.dumps(_edit(rng, listed)))
        kind = _outcome(parts, mutant, tmp_path / f"joined-{i}.pt")
        seen[kind] = seen.get(kind, 0) + 1
        mutant.unlink()
        (tmp_path / f"joined-{i}.pt").unlink(missing_ok=True)
    assert seen.get("refused", 0) > STRUCTURE_MUTANTS // 2, seen


def test_byte_mutants(parts, manifest, tmp_path) -> None:
    data = manifest.read_bytes()
    rng = np.random.default_rng(SEED + 1)
    seen: dict[str, int] = {}
    for i in range(BYTE_MUTANTS):
        out = bytearray(data)
        roll = rng.random()
        if roll < 0.1:  # nested deeper than Python's recursion limit, inside the manifest
            depth = int(rng.integers(1, 200_000))
            at = data.index(b'"parts"')
            out = bytearray(data[:at] + b'"deep": ' + b"[" * depth + b"]" * depth + b", " + data[at:])
        elif roll < 0.55:
            for _ in range(int(rng.integers(1, 6))):
                out[int(rng.integers(len(out)))] ^= 1 << int(rng.integers(8))
        else:
            at = int(rng.integers(len(out)))
            out = out[:at] + out[int(rng.integers(at, len(out) + 1)) :] * int(rng.integers(0, 3))
        mutant = manifest.parent / f"bytes-{i}.parts.json"
        mutant.write_bytes(bytes(out))
        kind = _outcome(parts, mutant, tmp_path / f"joined-{i}.pt")
        seen[kind] = seen.get(kind, 0) + 1
        mutant.unlink()
        (tmp_path / f"joined-{i}.pt").unlink(missing_ok=True)
    assert seen.get("refused", 0) > BYTE_MUTANTS // 2, seen
