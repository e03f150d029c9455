"""Byte mutations the file fuzzers share (``tests/robustness/test_*_fuzz.py``): bit flips, size-like
values written over any offset, truncation."""

from __future__ import annotations

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
