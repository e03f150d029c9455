"""What the file fuzzers share (``tests/robustness/test_*_fuzz.py``): byte mutations (bit flips,
size-like values written over any offset, truncation) and the one way a mutant's outcome is judged."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

#: Values that make size and offset fields interesting.
INTERESTING = [0, 1, 0x7F, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, 1 << 40, 2**64 - 1]


def byte_mutant(rng: np.random.Generator, data: bytes) -> bytes:
    """``data`` with a few bits flipped, an interesting value written over 2, 4 or 8 bytes, or cut."""
    out = bytearray(data)
    kind = rng.integers(3)
    if kind == 0:
        for _ in range(int(rng.integers(1, 8))):
            out[int(rng.integers(len(out)))] ^= 1 << int(rng.integers(8))
    elif kind == 1:
        value = INTERESTING[int(rng.integers(len(INTERESTING)))]
        width = int(rng.choice([2, 4, 8]))
        at = int(rng.integers(len(out) - width))
        out[at : at + width] = (value & ((1 << (8 * width)) - 1)).to_bytes(width, "little")
    else:
        del out[int(rng.integers(len(out))) :]
    return bytes(out)


def outcome(path: Path, read: Callable[[Path], object]) -> str:
    """``"ok"`` when ``read(path)`` succeeds, else the kind of its clean refusal: a ValueError or
    OSError that names the file in a message of reasonable length. Anything else propagates (the
    test fails)."""
    try:
        read(path)
    except (ValueError, OSError) as e:
        assert str(path) in str(e), f"the error does not name the file: {e}"
        assert len(str(e)) < 2000, f"an error message of {len(str(e))} characters"
        return type(e).__name__
    return "ok"


def outcomes(mutants: Iterable[bytes], folder: Path, read: Callable[[Path], object]) -> dict[str, int]:
    """How many of ``mutants`` (each written to a file in ``folder``, read, then removed) had each
    :func:`outcome`."""
    seen: dict[str, int] = {}
    for i, data in enumerate(mutants):
        path = folder / f"mutant-{i}.npz"
        path.write_bytes(data)
        kind = outcome(path, read)
        seen[kind] = seen.get(kind, 0) + 1
        path.unlink()
    return seen
