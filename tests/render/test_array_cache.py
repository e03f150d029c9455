"""lp3d.array_cache: folders built whole or not at all, and reused only when every check passes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lp3d import array_cache
from lp3d.array_cache import StaleCacheError

KEY = {"seed": 3, "sizes": [2, 4], "name": "tiny"}
SHAPES = {"planes": ((3, 2, 4), "float16"), "seed": ((3,), "int64")}


def _build(path: Path, key: dict = KEY) -> dict[str, np.ndarray]:
    want = {
        "planes": np.arange(24, dtype=np.float16).reshape(3, 2, 4) / 8,
        "seed": np.array([7, 8, 9], np.int64),
    }
    with array_cache.build(path, key, SHAPES) as out:
        assert isinstance(out["planes"], np.memmap) and out["planes"].shape == (3, 2, 4)
        for name, a in want.items():
            out[name][:] = a
    return want


def test_round_trip_and_nothing_else_left(tmp_path: Path) -> None:
    path = tmp_path / "cache" / array_cache.key_digest(KEY)
    want = _build(path)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # no temporary folder left
    assert sorted(p.name for p in path.iterdir()) == ["meta.json", "planes.npy", "seed.npy"]
    meta = json.loads((path / "meta.json").read_text())
    assert meta["key"] == KEY
    assert meta["arrays"]["seed"]["dtype"] == "int64" and meta["arrays"]["seed"]["shape"] == [3]
    assert meta["arrays"]["planes"]["sha256"] == array_cache.file_digest(path / "planes.npy")
    for mmap in (False, True):
        got = array_cache.load(path, KEY, SHAPES, mmap=mmap)
        assert isinstance(got["planes"], np.memmap) == mmap
        for name, a in want.items():
            np.testing.assert_array_equal(got[name], a)
            assert got[name].dtype == a.dtype


def test_key_digest_is_stable_and_order_free() -> None:
    assert array_cache.key_digest({"a": 1, "b": [2]}) == array_cache.key_digest({"b": [2], "a": 1})
    assert array_cache.key_digest({"a": 1}) != array_cache.key_digest({"a": 2})
    assert len(array_cache.key_digest(KEY)) == 20


class _Stale(StaleCacheError):
    pass


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        ("truncate", r"planes\.npy: its SHA-256 differs from meta\.json \(corrupt or edited\)"),
        ("flip-byte", r"seed\.npy: its SHA-256 differs"),
        ("delete", r"seed\.npy: missing"),
        ("meta-garbage", r"meta\.json: unreadable"),
        ("meta-digest", r"planes\.npy: its SHA-256 differs"),
        ("meta-shape", r"planes\.npy: meta\.json records shape \[3, 2, 5\] float16, expected \[3, 2, 4\]"),
        ("old-digest", r"planes\.npy: meta\.json records no SHA-256"),
        ("nan", r"planes\.npy: holds NaN or Inf"),
    ],
)
def test_damaged_folder_is_stale(tmp_path: Path, damage: str, match: str) -> None:
    path = tmp_path / "c"
    _build(path)
    meta_path = path / "meta.json"
    meta = json.loads(meta_path.read_text())
    planes = path / "planes.npy"
    if damage == "truncate":
        planes.write_bytes(planes.read_bytes()[:-10])
    elif damage == "flip-byte":
        raw = bytearray((path / "seed.npy").read_bytes())
        raw[-2] ^= 0x10
        (path / "seed.npy").write_bytes(bytes(raw))
    elif damage == "delete":
        (path / "seed.npy").unlink()
    elif damage == "meta-garbage":
        meta_path.write_text("{not json")
    elif damage == "meta-digest":
        meta["arrays"]["planes"]["sha256"] = "0" * 64
        meta_path.write_text(json.dumps(meta))
    elif damage == "meta-shape":
        meta["arrays"]["planes"]["shape"] = [3, 2, 5]
        meta_path.write_text(json.dumps(meta))
    elif damage == "old-digest":  # an older lp3d's BLAKE2 meta: stale, so it is rebuilt
        entry = meta["arrays"]["planes"]
        entry["blake2b"] = entry.pop("sha256")
        meta_path.write_text(json.dumps(meta))
    else:  # a NaN whose digest was recorded too: the content check still refuses it
        a = np.load(planes)
        a[0, 0, 0] = np.nan
        np.save(planes, a)
        meta["arrays"]["planes"]["sha256"] = array_cache.file_digest(planes)
        meta_path.write_text(json.dumps(meta))
    with pytest.raises(_Stale, match=match):
        array_cache.load(path, KEY, SHAPES, error=_Stale)


def test_other_key_names_the_difference(tmp_path: Path) -> None:
    path = tmp_path / "c"
    _build(path)
    with pytest.raises(StaleCacheError, match=r"meta\.json: made for another key \(seed: 3 -> 4\)"):
        array_cache.load(path, {**KEY, "seed": 4}, SHAPES)
    # Shapes the caller now expects that the folder was not built with.
    with pytest.raises(StaleCacheError, match=r"planes\.npy: meta\.json records shape"):
        array_cache.load(path, KEY, {**SHAPES, "planes": ((3, 2, 8), "float16")})
    assert issubclass(StaleCacheError, ValueError)


def test_a_failure_mid_build_leaves_nothing_behind(tmp_path: Path) -> None:
    path = tmp_path / "c"
    with pytest.raises(RuntimeError, match="teacher failed"), array_cache.build(path, KEY, SHAPES) as out:
        out["seed"][:] = 1
        raise RuntimeError("teacher failed")
    assert list(tmp_path.iterdir()) == []
    # ... and an interrupted build leaves a previous, complete folder untouched.
    want = _build(path)
    with pytest.raises(KeyboardInterrupt), array_cache.build(path, KEY, SHAPES):
        raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["c"]
    np.testing.assert_array_equal(array_cache.load(path, KEY, SHAPES)["seed"], want["seed"])


def test_reuse_reports_and_deletes_a_stale_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "c"
    assert array_cache.reuse(path, lambda: array_cache.load(path, KEY, SHAPES), "rebuilding") is None
    _build(path)
    got = array_cache.reuse(path, lambda: array_cache.load(path, KEY, SHAPES), "rebuilding")
    assert got is not None and capsys.readouterr().err == ""
    (path / "planes.npy").write_bytes(b"")
    assert (
        array_cache.reuse(path, lambda: array_cache.load(path, KEY, SHAPES), "cache rejected, rebuilding")
        is None
    )
    err = capsys.readouterr().err
    assert err.startswith("warning: cache rejected, rebuilding: ") and "planes.npy" in err
    assert not path.exists()


@pytest.mark.parametrize(
    ("shapes", "match"),
    [
        ({"../x": ((1,), "float32")}, r"array name '\.\./x'"),
        ({"a": ((-1,), "float32")}, r"shapes\['a'\]: shape"),
        ({"a": ((1,), "no-such-type")}, r"shapes\['a'\]: dtype"),
    ],
)
def test_bad_shapes_are_refused(tmp_path: Path, shapes: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match), array_cache.build(tmp_path / "c", KEY, shapes):
        pass
    assert list(tmp_path.iterdir()) == []
