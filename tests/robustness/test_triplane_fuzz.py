"""A file-format fuzzer for both triplane readers: mutated ``.npz`` files give a valid
triplane or a clear ValueError/OSError naming the file, never another exception, an abort or a hang.

* ``test_mutated_archives``: byte mutations (bit flips, interesting size values over any field,
  truncation, splices) of valid files and of the hostile seeds (zip64 size claims, a 1.5 TiB header
  claim). Each reader may refuse a different thing first here (the zip libraries differ), so only
  the contract is checked.
* ``test_mutated_entries``: one ``.npy`` entry mutated (header text or data), then zipped again
  with a correct CRC and size, so the mutation reaches the header grammar and the value checks,
  which both readers share: here they must also agree, accept for accept and key for key.

Hypothesis runs derandomized with bounded example counts, so the test is deterministic and fast;
the counts are the ``max_examples`` below (docs/reliability.md quotes them).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from support.triplane_files import (
    Entry,
    assert_same_triplane,
    build_zip,
    good_arrays,
    npy,
    npy_of,
    npz_bytes,
    outcome,
    planes_header,
    with_grid,
)

MUTATED_ARCHIVES = 300
MUTATED_ENTRIES = 400

#: Values that make size and offset fields interesting.
INTERESTING = [0, 1, 0x7F, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, 1 << 40, 2**64 - 16, 2**64 - 1]
#: Characters a ``.npy`` header is made of.
HEADER_CHARS = "{}()':, 0123456789<>|fiuUOTrueFalsdescrfortran_ordershape\n\\\""


def _seeds() -> list[bytes]:
    claims = []
    for size in (1 << 40, 2**64 - 16):
        claims.append(npz_bytes(good_arrays(), decoder_w1={"declared_size": size, "declared_csize": size}))
    huge = npy(planes_header("(3, 32, 65536, 65536)"), good_arrays()["planes"].tobytes())
    return [
        npz_bytes(good_arrays()),
        npz_bytes(with_grid(good_arrays(np.float16))),
        *claims,
        npz_bytes({**good_arrays(), "planes": huge}),
    ]


SEEDS = _seeds()


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


mutation = st.tuples(
    st.sampled_from(["flip", "byte", "value", "truncate", "splice", "header"]),
    st.floats(0.0, 1.0),
    st.integers(0, 2**64 - 1),
)


def mutate(data: bytes, ops: list[tuple[str, float, int]]) -> bytes:
    b = bytearray(data)
    for op, where, value in ops:
        i = min(int(where * len(b)), max(len(b) - 1, 0))
        if not b and op != "splice":
            continue
        if op == "flip":
            b[i] ^= 1 << (value % 8)
        elif op == "byte":
            b[i] = value % 256
        elif op == "value":
            width = (2, 4, 8)[value % 3]
            v = INTERESTING[(value >> 2) % len(INTERESTING)].to_bytes(8, "little")[:width]
            b[i : i + width] = v[: len(b) - i]
        elif op == "truncate":
            del b[i:]
        elif op == "splice":
            n = value % 64
            b[i:i] = b[i : i + n]
        elif op == "header":
            starts = [m.start() for m in re.finditer(re.escape(b"\x93NUMPY"), bytes(b))]
            if starts:
                s = starts[value % len(starts)]
                j = min(s + 10 + (value >> 8) % 80, len(b) - 1)
                b[j] = ord(HEADER_CHARS[(value >> 16) % len(HEADER_CHARS)])
    return bytes(b)


def key_named(message: str) -> str | None:
    m = re.search(r"key '([^']*)'", message)
    return m.group(1) if m else None


@settings(
    max_examples=MUTATED_ARCHIVES,
    deadline=None,
    derandomize=True,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(seed=st.sampled_from(range(len(SEEDS))), ops=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_archives(folder: Path, seed: int, ops: list[tuple[str, float, int]]) -> None:
    path = folder / "archive.npz"
    path.write_bytes(mutate(SEEDS[seed], ops))
    for reader in ("python", "rust"):
        kind, value = outcome(reader, path)  # any other exception fails the test
        event(f"{reader}: {kind}")
        if kind != "ok":
            assert str(path) in str(value), f"{reader}: {value}"


@settings(
    max_examples=MUTATED_ENTRIES,
    deadline=None,
    derandomize=True,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    grid=st.booleans(),
    which=st.integers(0, 100),
    ops=st.lists(mutation, min_size=1, max_size=3),
)
def test_mutated_entries(folder: Path, grid: bool, which: int, ops: list[tuple[str, float, int]]) -> None:
    arrays = {**good_arrays(), "source": np.array("fuzz"), "camera": _camera()}
    if grid:
        arrays = with_grid(arrays)
    entries = [Entry(f"{k}.npy", npy_of(v)) for k, v in arrays.items()]
    target = entries[which % len(entries)]
    target.data = mutate(target.data, ops)
    path = folder / "entries.npz"
    path.write_bytes(build_zip(entries))
    (py_kind, py), (rs_kind, rs) = outcome("python", path), outcome("rust", path)
    event(f"{py_kind} {key_named(str(py)) if py_kind != 'ok' else ''}")
    assert py_kind == rs_kind, f"python {py_kind}: {py}\nrust {rs_kind}: {rs}"
    if py_kind == "ok":
        assert_same_triplane(py, rs)
    else:
        assert key_named(str(py)) == key_named(str(rs)), f"python: {py}\nrust: {rs}"


def _camera() -> np.ndarray:
    from lp3d.render.camera import look_at_camera

    return look_at_camera(yaw_deg=10.0)
