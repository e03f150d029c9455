"""Both triplane readers, ``lp3d.render.triplane_io.load_triplane`` (Python) and ``lp3d_render.Triplane.load``
(Rust), judge every file of ``tests/support/triplane_files.py`` alike: both accept it and read the same
values, or both refuse it with the same kind of error (OSError or ValueError) naming the file and
the key. Cases that once aborted, panicked or hung a reader run in a subprocess with a time limit,
so a regression fails this test instead of killing or hanging pytest.

Also: the caps are the same in both languages and in ``docs/triplane-format.md``.
"""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import lp3d_render
from lp3d.render import triplane_io
from support.paths import REPO
from support.triplane_files import CASES, Case, assert_same_triplane, outcome

DOC = REPO / "docs" / "triplane-format.md"

#: Seconds an isolated load may take before it counts as a hang (the fixed readers take milliseconds).
HANG_LIMIT_S = 60

_CHILD = r"""
import json, sys
reader, path = sys.argv[1], sys.argv[2]
try:
    if reader == "python":
        from lp3d.render.triplane_io import load_triplane
        load_triplane(path)
    else:
        import lp3d_render
        lp3d_render.Triplane.load(path)
    print(json.dumps({"kind": "ok"}))
except (ValueError, OSError) as e:
    print(json.dumps({"kind": "OSError" if isinstance(e, OSError) else "ValueError", "message": str(e)}))
"""


def isolated_outcome(reader: str, path: Path) -> tuple[str, object]:
    """:func:`outcome` in a child process: an abort, a panic or a hang fails with a clear message."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", _CHILD, reader, str(path)],
            capture_output=True,
            text=True,
            timeout=HANG_LIMIT_S,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"the {reader} reader hung on {path} (no answer in {HANG_LIMIT_S} s)")
    assert done.returncode == 0, (
        f"the {reader} reader crashed (exit {done.returncode}): {done.stderr[-2000:]}"
    )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return result["kind"], result.get("message")


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_both_readers_agree(case: Case, tmp_path: Path) -> None:
    path = case.make(tmp_path)
    run = isolated_outcome if case.isolate else outcome
    results = {reader: run(reader, path) for reader in ("python", "rust")}
    if case.valid:
        for reader, (kind, value) in results.items():
            assert kind == "ok", f"{reader} refused a valid file: {value}"
        if not case.isolate:
            assert_same_triplane(results["python"][1], results["rust"][1])
        return
    want = case.error.__name__
    for reader, (kind, message) in results.items():
        assert kind == want, f"{reader}: expected {want}, got {kind}: {message}"
        assert isinstance(message, str) and str(path) in message, f"{reader}: {message}"
        if case.field:
            assert f"'{case.field}'" in message, f"{reader} should name '{case.field}': {message}"
        assert case.words in message, f"{reader}: {message}"


def test_case_list_covers_the_issue() -> None:
    names = {c.name for c in CASES}
    assert len(names) == len(CASES), "case names must be unique"
    for item in (1, 3, 4, 8):
        assert any(c.item == item for c in CASES), item
    assert sum(c.valid for c in CASES) >= 10


def test_fifo_does_not_hang_the_viewer(tmp_path: Path) -> None:
    """``lp3d-view`` loads with the Rust reader before opening a window: a FIFO is an error at once."""
    import os

    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "lp3d.cli", "view", "--screenshot", str(tmp_path / "s.png"), str(fifo)],
            capture_output=True,
            text=True,
            timeout=HANG_LIMIT_S,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"lp3d-view hung on a FIFO (no answer in {HANG_LIMIT_S} s)")
    assert done.returncode != 0
    assert "pipe.npz" in done.stderr and "FIFO" in done.stderr, done.stderr
    assert not (tmp_path / "s.png").exists()


# ---------------------------------------------------------------------------------------------- caps


def doc_limits() -> dict[str, int]:
    """The "Caps" table of docs/triplane-format.md: | `name` | value | meaning |."""
    text = DOC.read_text()
    section = text.split("## Caps", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `(\w+)` \| ([0-9 ]+)", section, flags=re.M)
    return {name: int(value.replace(" ", "")) for name, value in rows}


def test_caps_agree_across_languages_and_doc() -> None:
    assert lp3d_render.FILE_LIMITS == triplane_io.FILE_LIMITS
    assert doc_limits() == triplane_io.FILE_LIMITS


def test_writers_refuse_what_the_readers_refuse(tmp_path: Path) -> None:
    """Neither writer makes a file beyond the caps: a too-long ``source`` (both languages) and planes
    wider than ``max_plane_size`` (Python; the Rust type cannot even hold them)."""
    import numpy as np

    from lp3d.render.sample_scenes import coloured_sphere

    tri = coloured_sphere(size=8)
    long = "x" * (triplane_io.MAX_SOURCE_CHARS + 1)
    out = tmp_path / "t.npz"
    with pytest.raises(ValueError, match="key 'source'.*cap of 4096"):
        triplane_io.save_triplane(out, dataclasses.replace(tri, source=long))
    native = lp3d_render.Triplane(tri.planes, tri.w0, tri.b0, tri.w1, tri.b1, source=long)
    with pytest.raises(ValueError, match="source.*cap of 4096"):
        native.save(str(out))
    wide = np.zeros((3, 32, 2, triplane_io.MAX_PLANE_SIZE + 1), np.float16)
    with pytest.raises(ValueError, match="key 'planes'.*cap of 2048"):
        triplane_io.save_triplane(out, dataclasses.replace(tri, planes=wide))
    assert not out.exists() and not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="2048"):
        lp3d_render.Triplane(wide, tri.w0, tri.b0, tri.w1, tri.b1)
