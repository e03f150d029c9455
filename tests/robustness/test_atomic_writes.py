"""Every lp3d writer shares one atomic writer (``lp3d.atomic``): files get the permissions of any new
file (``0666 & ~umask``) whichever API wrote them, the umask is never changed to find that out (which
would race with other threads), and a set of outputs is published all or nothing."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from lp3d.atomic import StagedFiles, atomic_path, create_temp
from lp3d.errors import UserError
from lp3d.lift.model_package import save_model_package
from lp3d.outputs import Staged
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane

#: An unusual umask, so the expected mode (0640) is neither mkstemp's 0600 nor the common 0644.
UMASK = 0o027


@pytest.fixture
def umask() -> Iterator[int]:
    old = os.umask(UMASK)
    try:
        yield UMASK
    finally:
        os.umask(old)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_every_writer_gives_the_usual_permissions(
    umask: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    plain = tmp_path / "plain.txt"
    plain.write_text("made by open()")
    expected = 0o666 & ~umask
    assert mode(plain) == expected

    # Reading the umask with os.umask() sets it to 0 for a moment, for every thread: not allowed.
    def no_umask(mask: int) -> int:
        raise AssertionError("os.umask called while writing (not thread-safe)")

    monkeypatch.setattr(os, "umask", no_umask)
    tri = coloured_sphere(size=8)
    written: dict[str, Path] = {}

    written["triplane_io.save_triplane"] = tmp_path / "py.npz"
    save_triplane(written["triplane_io.save_triplane"], tri)

    written["lp3d_render.Triplane.save"] = tmp_path / "rust.npz"
    tri.to_native().save(written["lp3d_render.Triplane.save"])

    written["atomic_path"] = tmp_path / "a.json"
    with atomic_path(written["atomic_path"]) as tmp:
        tmp.write_text("{}")

    bounds = {"box_warp": tri.box_warp, "ray_start": tri.ray_start, "ray_end": tri.ray_end}
    config = {"name": "tiny", "image_size": 64, "triplane_resolution": 8}
    written["save_model_package"] = save_model_package(
        tmp_path / "m.onnx", (tri.w0, tri.b0, tri.w1, tri.b1), config, bounds
    )

    for name, group in (("atomic.StagedFiles", StagedFiles), ("outputs.Staged", Staged)):
        written[name] = tmp_path / f"{name}.png"
        with group() as staged:
            staged.temp(written[name]).write_bytes(b"png")
            staged.commit()

    modes = {name: oct(mode(path)) for name, path in written.items()}
    assert modes == {name: oct(expected) for name in written}


def test_temporary_files_are_new_and_distinct(umask: int, tmp_path: Path) -> None:
    dest = tmp_path / "x.npz"
    temps = {create_temp(dest) for _ in range(50)}
    assert len(temps) == 50
    for tmp in temps:
        assert tmp.parent == tmp_path and tmp.name.startswith(".x.npz.") and tmp.suffix == ".npz"
        assert tmp.stat().st_size == 0 and mode(tmp) == 0o666 & ~umask


@pytest.mark.parametrize(
    ("group", "error"), [(StagedFiles, OSError), (Staged, UserError)], ids=["StagedFiles", "outputs.Staged"]
)
def test_staged_outputs_are_published_all_or_none(tmp_path: Path, group: type, error: type) -> None:
    (tmp_path / "second.png" / "inside").mkdir(parents=True)  # a folder where a file should go
    with pytest.raises(error, match="second.png"), group() as staged:
        staged.mkdir(tmp_path / "new")
        staged.temp(tmp_path / "new" / "first.png").write_bytes(b"first")
        staged.temp(tmp_path / "second.png").write_bytes(b"second")
        staged.commit()
    # first.png was renamed into place before second.png failed: it is removed again, and so is the
    # folder made for it.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["second.png"]


def test_failed_block_leaves_nothing(tmp_path: Path) -> None:
    dest = tmp_path / "keep.npz"
    dest.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(dest) as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("simulated")
    assert dest.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.npz"]
