"""lp3d.render.triplane and lp3d.render.triplane_io: validation, the .npz format, atomic writes, bad files."""

from __future__ import annotations

import dataclasses
import math
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from lp3d.render import triplane_io
from lp3d.render.camera import look_at_camera
from lp3d.render.triplane import PLANE_AXES, TriplaneData, TriplaneError, effective_decoder_weights
from lp3d.render.triplane_io import FORMAT_VERSION, load_triplane, save_triplane


def make_triplane(dtype: type = np.float32, *, optional: bool = False, size: int = 6) -> TriplaneData:
    rng = np.random.default_rng(1)
    extra: dict[str, object] = {}
    if optional:
        extra = {
            "camera": look_at_camera(yaw_deg=10.0),
            "source": "procedural teacher, seed 7 — ünïcode",
        }
    tri = TriplaneData(
        planes=rng.normal(size=(3, 32, size, size + 1)).astype(dtype),
        w0=rng.normal(size=(64, 32)).astype(np.float32),
        b0=rng.normal(size=64).astype(np.float32),
        w1=rng.normal(size=(33, 64)).astype(np.float32),
        b1=rng.normal(size=33).astype(np.float32),
        box_warp=1.0,
        ray_start=2.25,
        ray_end=3.3,
        **extra,  # type: ignore[arg-type]
    )
    # A grid must bound its planes' density to be saved: the renderer's own bake.
    return dataclasses.replace(tri, occupancy=tri.to_native().bake_occupancy(4)) if optional else tri


def good_arrays(dtype: type = np.float32) -> dict[str, np.ndarray]:
    """The arrays of a valid file, written by hand (independent of the writer)."""
    tri = make_triplane(dtype)
    return {
        "planes": tri.planes,
        "decoder_w0": tri.w0,
        "decoder_b0": tri.b0,
        "decoder_w1": tri.w1,
        "decoder_b1": tri.b1,
        "box_warp": np.array(1.0),
        "ray_start": np.array(2.25),
        "ray_end": np.array(3.3),
        "format_version": np.array(1),
    }


def assert_same(a: TriplaneData, b: TriplaneData) -> None:
    assert a.planes.dtype == b.planes.dtype
    for name in ("planes", "w0", "b0", "w1", "b1"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert (a.box_warp, a.ray_start, a.ray_end, a.source) == (b.box_warp, b.ray_start, b.ray_end, b.source)
    for name in ("camera", "occupancy"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None)
        if x is not None:
            np.testing.assert_array_equal(x, y)
            assert x.dtype == y.dtype


# ------------------------------------------------------------------------------------------ TriplaneData


def test_plane_axes_keep_eg3d_quirk() -> None:
    assert PLANE_AXES == ((0, 1), (0, 2), (2, 0))


def test_weights_float64_are_stored_float32() -> None:
    tri = make_triplane()
    tri2 = TriplaneData(planes=tri.planes, w0=tri.w0.astype(np.float64), b0=tri.b0, w1=tri.w1, b1=tri.b1)
    assert tri2.w0.dtype == np.float32
    assert tri2.box_warp == 1.0 and tri2.ray_start == 2.25 and tri2.ray_end == 3.3


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"planes": np.zeros((3, 32, 4, 4), np.float64)}, "planes"),
        ({"planes": np.zeros((3, 31, 4, 4), np.float32)}, "planes"),
        ({"planes": np.zeros((2, 32, 4, 4), np.float32)}, "planes"),
        ({"planes": np.zeros((3, 32, 1, 4), np.float32)}, "planes"),
        ({"planes": np.full((3, 32, 4, 4), np.inf, np.float16)}, "planes"),
        ({"w0": np.zeros((32, 64), np.float32)}, "w0"),
        ({"b0": np.zeros(64, np.int32)}, "b0"),
        ({"w1": np.full((33, 64), np.nan)}, "w1"),
        ({"b1": np.zeros(32)}, "b1"),
        ({"box_warp": 0.0}, "box_warp"),
        ({"box_warp": math.inf}, "box_warp"),
        ({"ray_start": -1.0}, "ray_start"),
        ({"ray_end": 2.0}, "ray_end"),
        ({"ray_end": math.nan}, "ray_end"),
        ({"camera": np.zeros(25)}, "camera"),
        ({"camera": np.stack([look_at_camera()] * 2)}, "camera"),
        ({"occupancy": np.zeros((4, 4), np.float32)}, "occupancy"),
        ({"occupancy": np.full((2, 2, 2), np.nan, np.float32)}, "occupancy"),
        ({"source": 3}, "source"),
    ],
)
def test_triplane_validation_names_field(change: dict[str, object], field: str) -> None:
    tri = make_triplane()
    kwargs: dict[str, object] = {
        "planes": tri.planes,
        "w0": tri.w0,
        "b0": tri.b0,
        "w1": tri.w1,
        "b1": tri.b1,
    }
    kwargs.update(change)
    with pytest.raises(TriplaneError, match=f"^{field}: ") as info:
        TriplaneData(**kwargs)  # type: ignore[arg-type]
    assert info.value.field == field
    assert isinstance(info.value, ValueError)


def test_effective_decoder_weights() -> None:
    w0 = np.ones((64, 32), np.float32)
    w1 = np.full((33, 64), 2.0, np.float32)
    b0 = np.arange(64, dtype=np.float32)
    b1 = np.arange(33, dtype=np.float32)
    ew0, eb0, ew1, eb1 = effective_decoder_weights(w0, b0, w1, b1)
    np.testing.assert_allclose(ew0, 1 / math.sqrt(32), rtol=1e-7)
    np.testing.assert_array_equal(ew1, 2.0 / 8.0)
    np.testing.assert_array_equal(eb0, b0)
    np.testing.assert_array_equal(eb1, b1)
    assert all(a.dtype == np.float32 for a in (ew0, eb0, ew1, eb1))
    ew0, eb0, ew1, eb1 = effective_decoder_weights(w0, b0, w1, b1, lr_multiplier=2.0)
    np.testing.assert_allclose(ew0, 2 / math.sqrt(32), rtol=1e-7)
    np.testing.assert_array_equal(ew1, 0.5)
    np.testing.assert_array_equal(eb1, 2 * b1)
    # Torch's rounding: float32 weight times the gain rounded to float32.
    w = np.random.default_rng(0).normal(size=(64, 32)).astype(np.float32)
    np.testing.assert_array_equal(
        effective_decoder_weights(w, b0, w1, b1)[0], w * np.float32(1 / math.sqrt(32))
    )


# ------------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
@pytest.mark.parametrize("optional", [False, True])
def test_round_trip(tmp_path: Path, dtype: type, optional: bool) -> None:
    tri = make_triplane(dtype, optional=optional)
    path = tmp_path / "portrait.npz"
    save_triplane(path, tri)
    back = load_triplane(path)
    assert back.planes.dtype == dtype
    assert_same(tri, back)
    assert sorted(os.listdir(tmp_path)) == ["portrait.npz"]  # no temp file left behind


def test_file_layout_is_plain_little_endian(tmp_path: Path) -> None:
    tri = make_triplane(np.float16, optional=True)
    path = tmp_path / "portrait.tri"  # the exact name is used: no ".npz" appended
    save_triplane(path, tri)
    assert path.exists()
    with np.load(path, allow_pickle=False) as npz:
        assert set(npz.files) == {
            "planes",
            "decoder_w0",
            "decoder_b0",
            "decoder_w1",
            "decoder_b1",
            "box_warp",
            "ray_start",
            "ray_end",
            "format_version",
            "camera",
            "occupancy",
            "occupancy_checksum",
            "source",
        }
        assert npz["planes"].dtype.str == "<f2"
        assert npz["decoder_w0"].dtype.str == "<f4"
        assert npz["box_warp"].shape == () and npz["box_warp"].dtype.str == "<f8"
        assert npz["format_version"].dtype.str == "<i8" and int(npz["format_version"]) == FORMAT_VERSION
        assert npz["source"].shape == () and npz["source"].dtype.kind == "U"
        assert npz["camera"].dtype.str == "<f8" and npz["occupancy"].dtype.str == "<f4"
        assert npz["occupancy_checksum"].shape == () and npz["occupancy_checksum"].dtype.str == "<i8"
    with zipfile.ZipFile(path) as zf:
        assert all(info.compress_type == zipfile.ZIP_STORED for info in zf.infolist())


def test_fortran_ordered_planes_are_written_c_ordered(tmp_path: Path) -> None:
    tri = make_triplane()
    f_planes = np.asfortranarray(tri.planes)
    save_triplane(
        tmp_path / "t.npz", TriplaneData(planes=f_planes, w0=tri.w0, b0=tri.b0, w1=tri.w1, b1=tri.b1)
    )
    with zipfile.ZipFile(tmp_path / "t.npz") as zf, zf.open("planes.npy") as f:
        header = f.read(128)
    assert b"'fortran_order': False" in header
    np.testing.assert_array_equal(load_triplane(tmp_path / "t.npz").planes, tri.planes)


def test_loads_hand_written_file_with_float64_weights(tmp_path: Path) -> None:
    arrays = good_arrays()
    arrays["decoder_w1"] = arrays["decoder_w1"].astype(np.float64)
    arrays["format_version"] = np.array(1, dtype=np.int32)
    arrays["camera"] = look_at_camera().astype(np.float32)  # what the Rust writer produces
    np.savez(tmp_path / "t.npz", **arrays)
    tri = load_triplane(tmp_path / "t.npz")
    assert tri.w1.dtype == np.float32 and tri.camera is not None and tri.camera.dtype == np.float64


# ------------------------------------------------------------------------------------------- atomicity


def _failing_savez(file: object, **arrays: np.ndarray) -> None:
    file.write(b"PK\x03\x04 partial garbage")  # type: ignore[attr-defined]
    raise RuntimeError("disk full (simulated)")


def test_failed_write_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(triplane_io.np, "savez", _failing_savez)
    with pytest.raises(RuntimeError, match="disk full"):
        save_triplane(tmp_path / "new.npz", make_triplane())
    assert os.listdir(tmp_path) == []


def test_failed_write_keeps_existing_target(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "portrait.npz"
    save_triplane(path, make_triplane(np.float16))
    before = path.read_bytes()
    monkeypatch.setattr(triplane_io.np, "savez", _failing_savez)
    with pytest.raises(RuntimeError):
        save_triplane(path, make_triplane(np.float32))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["portrait.npz"]


def test_failed_rename_leaves_no_temp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def failing_replace(src: str, dst: str) -> None:
        raise OSError("rename refused (simulated)")

    monkeypatch.setattr(triplane_io.os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename refused"):
        save_triplane(tmp_path / "x.npz", make_triplane())
    assert os.listdir(tmp_path) == []


def test_invalid_triplane_is_not_written(tmp_path: Path) -> None:
    tri = make_triplane()
    tri.planes[0, 0, 0, 0] = np.nan  # mutated after construction: save re-validates
    with pytest.raises(ValueError, match="planes"):
        save_triplane(tmp_path / "x.npz", tri)
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------------------- bad files


def _write(tmp_path: Path, arrays: dict[str, np.ndarray]) -> Path:
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    return path


def _expect(path: Path, key: str | None, pattern: str = "") -> None:
    with pytest.raises(ValueError) as info:
        load_triplane(path)
    message = str(info.value)
    assert str(path) in message
    if key is not None:
        assert f"'{key}'" in message, message
    if pattern:
        assert pattern in message, message


@pytest.mark.parametrize("key", ["planes", "decoder_b1", "ray_end", "format_version"])
def test_missing_key(tmp_path: Path, key: str) -> None:
    arrays = good_arrays()
    del arrays[key]
    _expect(_write(tmp_path, arrays), key, "missing")


def test_object_array(tmp_path: Path) -> None:
    arrays = good_arrays()
    arrays["planes"] = np.array([1, "a", None], dtype=object)
    _expect(_write(tmp_path, arrays), "planes")


def test_unknown_format_version(tmp_path: Path) -> None:
    arrays = good_arrays()
    arrays["format_version"] = np.array(2)
    arrays["something_new"] = np.zeros(3)  # reported as a version problem, not as an extra key
    _expect(_write(tmp_path, arrays), "format_version", "unknown format_version 2")


def test_non_integer_format_version(tmp_path: Path) -> None:
    arrays = good_arrays()
    arrays["format_version"] = np.array(1.0)
    _expect(_write(tmp_path, arrays), "format_version")


def test_extra_key(tmp_path: Path) -> None:
    arrays = good_arrays()
    arrays["notes"] = np.zeros(2)
    _expect(_write(tmp_path, arrays), "notes", "unknown key")


@pytest.mark.parametrize("fraction", [0.0, 0.3, 0.9, 0.999])
def test_truncated_file(tmp_path: Path, fraction: float) -> None:
    path = tmp_path / "t.npz"
    save_triplane(path, make_triplane())
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    _expect(path, None)


def test_corrupt_member_names_key(tmp_path: Path) -> None:
    tri = make_triplane()
    path = tmp_path / "t.npz"
    save_triplane(path, tri)
    data = bytearray(path.read_bytes())
    at = bytes(data).find(tri.planes.tobytes()[:64])
    assert at > 0
    data[at + 100] ^= 0xFF  # flip bits inside the planes payload: the zip CRC no longer matches
    path.write_bytes(bytes(data))
    _expect(path, "planes")


def test_not_a_zip(tmp_path: Path) -> None:
    path = tmp_path / "t.npz"
    path.write_bytes(b"hello, this is not a triplane at all\n" * 10)
    _expect(path, None)


def test_single_npy_file(tmp_path: Path) -> None:
    path = tmp_path / "t.npz"
    with open(path, "wb") as f:
        np.save(f, np.zeros(3))
    _expect(path, None, "not an .npz")


def test_missing_file_is_oserror(tmp_path: Path) -> None:
    with pytest.raises(OSError) as info:
        load_triplane(tmp_path / "nope.npz")
    assert "nope.npz" in str(info.value)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("planes", np.zeros((3, 32, 4), np.float32)),
        ("planes", np.zeros((3, 32, 4, 4), np.float64)),
        ("planes", np.zeros((3, 32, 4, 4), np.int16)),
        ("decoder_w0", np.zeros((32, 64), np.float32)),
        ("decoder_b0", np.zeros(64, np.int64)),
        ("decoder_w1", np.zeros((33, 63), np.float32)),
        ("decoder_b1", np.zeros((1, 33), np.float32)),
        ("box_warp", np.array([1.0])),
        ("box_warp", np.array(-1.0)),
        ("ray_start", np.array("2.25")),
        ("ray_end", np.array(1.0)),
        ("camera", np.zeros(24)),
        ("camera", np.zeros(25)),
        ("occupancy", np.zeros((4, 4), np.float32)),
        ("occupancy", np.zeros((4, 4, 4), np.float64)),
        ("source", np.array(["a", "b"])),
        ("source", np.array(3)),
    ],
)
def test_bad_shape_dtype_or_value(tmp_path: Path, key: str, value: np.ndarray) -> None:
    arrays = good_arrays()
    arrays[key] = value
    _expect(_write(tmp_path, arrays), key)


@pytest.mark.parametrize("key", ["planes", "decoder_w0", "decoder_b0", "decoder_w1", "decoder_b1"])
def test_nan_is_rejected(tmp_path: Path, key: str) -> None:
    arrays = good_arrays(np.float16)
    arrays[key] = arrays[key].copy()
    arrays[key].flat[3] = np.nan
    _expect(_write(tmp_path, arrays), key, "NaN")
