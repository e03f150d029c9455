"""Concurrent saves and loads of one triplane path, from threads and from processes.

Several threads of this process and two child processes save *different* triplanes to the same path
while other threads load it. Every save must succeed; every load must return one saver's triplane
whole (its planes, decoder and source agree), or, only while no save has finished yet, a clean "no
such file". Nothing else is allowed: no "Could not find EOCD", no "Invalid checksum", no half file,
no leftover temporary file. Run for ``lp3d_render.Triplane`` (Rust) and ``lp3d.render.triplane_io``.

The work is bounded by counts (savers x saves), not by time; each case takes a second or two.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from support.paths import TESTS

SAVER_THREADS = 3
SAVES_PER_THREAD = 20
PROCESSES = 2
SAVES_PER_PROCESS = 20
LOADER_THREADS = 2
#: Plane side: big enough (~400 KB per file) that writes take long enough to overlap.
SIDE = 32

Save = Callable[[Path, int], None]
Load = Callable[[Path], int]


def marked_arrays(marker: int) -> dict[str, np.ndarray]:
    """A valid triplane whose every array carries ``marker``, so a mix of two files is visible."""
    value = np.float32(marker / 64.0)
    return {
        "planes": np.full((3, 32, SIDE, SIDE), value, np.float32),
        "w0": np.full((64, 32), value, np.float32),
        "b0": np.full(64, value, np.float32),
        "w1": np.full((33, 64), value, np.float32),
        "b1": np.full(33, value, np.float32),
    }


def marker_of(planes: np.ndarray, w1: np.ndarray, b1: np.ndarray, source: str | None) -> int:
    """The marker of a loaded triplane; fails if its parts come from different savers."""
    marker = round(float(planes.flat[0]) * 64.0)
    expected = marked_arrays(marker)
    assert np.array_equal(planes, expected["planes"]), "planes are not one saver's"
    assert np.array_equal(w1, expected["w1"]) and np.array_equal(b1, expected["b1"]), "decoder mix"
    assert source == f"saver {marker}", f"source {source!r} does not match marker {marker}"
    return marker


def rust_save(path: Path, marker: int) -> None:
    import lp3d_render

    a = marked_arrays(marker)
    tri = lp3d_render.Triplane(a["planes"], a["w0"], a["b0"], a["w1"], a["b1"], source=f"saver {marker}")
    tri.save(path)


def rust_load(path: Path) -> int:
    import lp3d_render

    tri = lp3d_render.Triplane.load(path)
    return marker_of(tri.planes, tri.w1, tri.b1, tri.source)


def python_save(path: Path, marker: int) -> None:
    from lp3d.render.triplane import TriplaneData
    from lp3d.render.triplane_io import save_triplane

    save_triplane(path, TriplaneData(**marked_arrays(marker), source=f"saver {marker}"))


def python_load(path: Path) -> int:
    from lp3d.render.triplane_io import load_triplane

    tri = load_triplane(path)
    return marker_of(tri.planes, tri.w1, tri.b1, tri.source)


APIS: dict[str, tuple[Save, Load]] = {"rust": (rust_save, rust_load), "python": (python_save, python_load)}


def is_not_found(e: BaseException) -> bool:
    return isinstance(e, FileNotFoundError) or (isinstance(e, OSError) and "No such file" in str(e))


def load_checked(load: Load, path: Path) -> int | None:
    """One load: a marker, or None for a clean "no such file" while the file did not exist yet
    (files only ever appear, never disappear, so existing before the call rules that out)."""
    existed = path.exists()
    try:
        return load(path)
    except Exception as e:
        if not existed and is_not_found(e):
            return None
        raise AssertionError(f"load failed: {type(e).__name__}: {e}") from e


# A child process: waits for "go" on stdin, then saves (and checks a load after each save).
CHILD = """
import sys
from pathlib import Path
sys.path[:0] = [{here!r}, {tests!r}]
import test_concurrency as t
save, load = t.APIS[{api!r}]
path, first = Path({path!r}), {first}
print("ready", flush=True)
assert sys.stdin.readline().strip() == "go"
for i in range({saves}):
    save(path, first + i % 4)
    t.load_checked(load, path)
print("done", flush=True)
"""


@pytest.mark.parametrize("api", sorted(APIS))
def test_concurrent_saves_and_loads(api: str, tmp_path: Path) -> None:
    save, load = APIS[api]
    path = tmp_path / "shared.npz"
    errors: list[str] = []
    loads: list[int | None] = []
    saving = threading.Event()
    saving.set()

    # Children first (their start-up is the slow part); they wait for "go".
    children = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                CHILD.format(
                    here=str(Path(__file__).parent),
                    tests=str(TESTS),
                    api=api,
                    path=str(path),
                    first=100 + 10 * c,
                    saves=SAVES_PER_PROCESS,
                ),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for c in range(PROCESSES)
    ]
    for child in children:
        assert child.stdout is not None and child.stdout.readline().strip() == "ready", child.communicate()[1]

    def saver(t: int) -> None:
        try:
            for i in range(SAVES_PER_THREAD):
                save(path, 10 * t + i % 4)
        except Exception as e:
            errors.append(f"saver thread {t}: {type(e).__name__}: {e}")

    def loader() -> None:
        try:
            while saving.is_set():
                loads.append(load_checked(load, path))
        except AssertionError as e:
            errors.append(str(e))

    savers = [threading.Thread(target=saver, args=(t,)) for t in range(SAVER_THREADS)]
    loaders = [threading.Thread(target=loader) for _ in range(LOADER_THREADS)]
    for th in loaders + savers:
        th.start()
    outputs = [child.communicate("go\n", timeout=300) for child in children]
    for th in savers:
        th.join()
    saving.clear()
    for th in loaders:
        th.join()

    for child, (out, err) in zip(children, outputs, strict=True):
        assert child.returncode == 0 and out.strip().endswith("done"), f"child process failed:\n{err}"
    assert not errors, f"{len(errors)} failures, first: {errors[:3]}"
    assert any(m is not None for m in loads), "no load saw a file"
    # The last rename wins and every save published a whole file; no temporary file is left.
    final = load(path)
    assert final in {10 * t + i for t in range(SAVER_THREADS) for i in range(4)} | {
        100 + 10 * c + i for c in range(PROCESSES) for i in range(4)
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shared.npz"]
