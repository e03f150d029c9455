"""Every bad input gives a Python exception (ValueError or OSError) whose message names the bad
field, never a crash, and nothing is written when a call fails."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

import lp3d_render
from support.scenes import PARITY_CAMERAS, make_scene

KW = {"resolution": 5, "depth_resolution": 12, "depth_resolution_importance": 12}


@pytest.fixture(scope="module")
def parts() -> dict[str, np.ndarray]:
    s = make_scene(size=(8, 8)).data
    return {"planes": s.planes, "w0": s.w0, "b0": s.b0, "w1": s.w1, "b1": s.b1}


def build(parts: dict, **override):
    p = {**parts, **override}
    extra = {k: p.pop(k) for k in ("box_warp", "ray_start", "ray_end") if k in p}
    return lp3d_render.Triplane(p["planes"], p["w0"], p["b0"], p["w1"], p["b1"], **extra)


@pytest.mark.parametrize(
    ("override", "field", "words"),
    [
        ({"planes": np.zeros((3, 31, 8, 8), np.float32)}, "planes", "shape"),
        ({"planes": np.zeros((32, 8, 8), np.float32)}, "planes", "shape"),
        ({"planes": np.zeros((3, 32, 1, 8), np.float32)}, "planes", "H and W"),
        ({"planes": np.zeros((3, 32, 8, 8), np.float64)}, "planes", "dtype"),
        ({"planes": np.zeros((3, 32, 8, 8), np.int32)}, "planes", "dtype"),
        ({"planes": [[1.0]]}, "planes", "numpy array"),
        ({"w0": np.zeros((32, 64), np.float32)}, "w0", "shape"),
        ({"b0": np.zeros(63, np.float32)}, "b0", "shape"),
        ({"w1": np.zeros((33, 64), np.int64)}, "w1", "dtype"),
        ({"b1": np.zeros(32, np.float32)}, "b1", "shape"),
        ({"box_warp": 0.0}, "box_warp", "> 0"),
        ({"box_warp": float("nan")}, "box_warp", "finite"),
        ({"ray_start": -1.0}, "ray_start", ">= 0"),
        ({"ray_start": 3.3, "ray_end": 3.3}, "ray_end", "> ray_start"),
        ({"ray_start": 3.0, "ray_end": 2.0}, "ray_end", "> ray_start"),
        ({"ray_end": float("inf")}, "ray_end", "finite"),
    ],
)
def test_bad_triplane(parts, override, field, words) -> None:
    with pytest.raises(ValueError, match=field) as e:
        build(parts, **override)
    assert words in str(e.value)


@pytest.mark.parametrize("name", ["planes", "w0", "b0", "w1", "b1"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_arrays(parts, name, bad) -> None:
    arr = parts[name].copy()
    arr.flat[3] = bad
    with pytest.raises(ValueError, match=rf"{name}: contains NaN/Inf"):
        build(parts, **{name: arr})


def camera_with(index: int, value: float) -> np.ndarray:
    c = PARITY_CAMERAS["frontal"].copy()
    c[index] = value
    return c


@pytest.mark.parametrize(
    ("camera", "words"),
    [
        (np.zeros(24), "shape must be (25,) or (B, 25)"),
        (np.zeros((2, 3, 25)), "shape must be (25,) or (B, 25)"),
        (np.zeros((0, 25)), "shape must be (25,) or (B, 25)"),
        (np.zeros(25, dtype=np.int64), "dtype must be float32 or float64"),
        ("frontal", "expected a numpy array"),
        (camera_with(5, np.nan), "NaN/Inf at index 5"),
        (camera_with(3, np.inf), "NaN/Inf at index 3"),
        (camera_with(16, 0.0), "focal"),
        (camera_with(20, -4.0), "focal"),
        (camera_with(15, 2.0), "cam2world"),
        (np.concatenate([np.zeros(12), [0, 0, 0, 1], PARITY_CAMERAS["frontal"][16:]]), "singular"),
        (camera_with(24, 2.0), "intrinsics"),
    ],
)
def test_bad_camera(gpu, camera, words) -> None:
    tri = make_scene(size=(8, 8)).native
    with pytest.raises(ValueError, match="camera") as e:
        lp3d_render.render(tri, camera, **KW)
    assert words in str(e.value)


def test_bad_camera_in_a_batch_names_its_index(gpu) -> None:
    tri = make_scene(size=(8, 8)).native
    batch = np.stack([PARITY_CAMERAS["frontal"], camera_with(20, 0.0)])
    with pytest.raises(ValueError, match=r"camera\[1\] focal"):
        lp3d_render.render(tri, batch, **KW)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"resolution": 0}, "resolution"),
        ({"resolution": 1025}, "resolution"),
        ({"resolution": -3}, "resolution"),
        ({"depth_resolution": 1}, "depth_resolution"),
        ({"depth_resolution": 3}, "depth_resolution"),  # importance sampling needs >= 4
        ({"depth_resolution": 257}, "depth_resolution"),
        ({"depth_resolution_importance": 1}, "depth_resolution_importance"),
        ({"depth_resolution_importance": -2}, "depth_resolution_importance"),
        ({"outputs": ["rgb", "normals"]}, "outputs"),
        ({"outputs": []}, "outputs"),
        ({"seed": 3}, "seed"),  # a seed only applies to jittered rendering
        ({"deterministic": False, "seed": -1}, "seed"),
        ({"transmittance_threshold": 1.0}, "transmittance_threshold"),
        ({"transmittance_threshold": -0.1}, "transmittance_threshold"),
        ({"empty_threshold": float("nan")}, "empty_threshold"),
    ],
)
def test_bad_settings(gpu, kwargs, field) -> None:
    tri = make_scene(size=(8, 8)).native
    with pytest.raises(ValueError, match=field):
        lp3d_render.render(tri, PARITY_CAMERAS["frontal"], **{**KW, **kwargs})


def test_not_a_triplane(gpu) -> None:
    with pytest.raises(ValueError, match="triplane: expected lp3d_render.Triplane"):
        lp3d_render.render({"planes": 1}, PARITY_CAMERAS["frontal"])


# --------------------------------------------------------------------------- files (Rust reader)


@pytest.fixture()
def good_file(tmp_path: Path) -> Path:
    path = tmp_path / "good.npz"
    make_scene(size=(8, 8)).native.save(path)
    return path


def rewrite(src: Path, dst: Path, *, drop: str | None = None, replace: dict | None = None) -> Path:
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != drop}
    arrays.update(replace or {})
    np.savez(dst, **arrays)
    return dst


@pytest.mark.parametrize(
    "key",
    [
        "planes",
        "decoder_w0",
        "decoder_b0",
        "decoder_w1",
        "decoder_b1",
        "box_warp",
        "ray_start",
        "ray_end",
        "format_version",
    ],
)
def test_missing_key(good_file: Path, tmp_path: Path, key: str) -> None:
    bad = rewrite(good_file, tmp_path / "bad.npz", drop=key)
    with pytest.raises(ValueError, match=rf"bad.npz: key '{key}': missing"):
        lp3d_render.Triplane.load(bad)


def test_unknown_format_version(good_file: Path, tmp_path: Path) -> None:
    bad = rewrite(good_file, tmp_path / "bad.npz", replace={"format_version": np.int64(2)})
    with pytest.raises(ValueError, match="key 'format_version': unknown format_version 2 "):
        lp3d_render.Triplane.load(bad)


def test_object_array_is_refused_without_unpickling(good_file: Path, tmp_path: Path) -> None:
    with np.load(good_file) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["source"] = np.array([{"evil": 1}], dtype=object)
    bad = tmp_path / "bad.npz"
    np.savez(bad, allow_pickle=True, **arrays)
    with pytest.raises(ValueError, match="key 'source': object arrays are not allowed"):
        lp3d_render.Triplane.load(bad)


@pytest.mark.parametrize(
    ("replace", "key", "words"),
    [
        ({"planes": np.zeros((3, 32, 8), np.float32)}, "planes", "shape"),
        ({"planes": np.zeros((3, 32, 8, 8), np.int16)}, "planes", "unsupported dtype"),
        ({"decoder_w1": np.zeros((64, 33), np.float32)}, "decoder_w1", "shape"),
        ({"ray_end": np.float64(1.0)}, "ray_end", "> ray_start"),
        ({"planes": np.full((3, 32, 8, 8), np.nan, np.float32)}, "planes", "NaN"),
        ({"camera": np.zeros(25)}, "camera", "cam2world"),
        ({"extra": np.zeros(3)}, "extra", "unknown key"),
        ({"source": np.array(3.0)}, "source", "string"),
    ],
)
def test_bad_contents(good_file: Path, tmp_path: Path, replace, key, words) -> None:
    bad = rewrite(good_file, tmp_path / "bad.npz", replace=replace)
    with pytest.raises(ValueError, match=rf"key '{key}'") as e:
        lp3d_render.Triplane.load(bad)
    assert words in str(e.value)


def test_truncated_and_corrupt_files(good_file: Path, tmp_path: Path) -> None:
    data = good_file.read_bytes()
    for n in (0, 10, len(data) // 2, len(data) - 30):
        bad = tmp_path / f"trunc{n}.npz"
        bad.write_bytes(data[:n])
        with pytest.raises(ValueError, match=f"trunc{n}.npz"):
            lp3d_render.Triplane.load(bad)
    # A valid zip whose member is a truncated .npy.
    buf = io.BytesIO()
    with zipfile.ZipFile(good_file) as zin, zipfile.ZipFile(buf, "w") as zout:
        for info in zin.infolist():
            raw = zin.read(info)
            zout.writestr(info.filename, raw[: len(raw) // 2] if info.filename == "planes.npy" else raw)
    bad = tmp_path / "short-member.npz"
    bad.write_bytes(buf.getvalue())
    with pytest.raises(ValueError, match="key 'planes': truncated"):
        lp3d_render.Triplane.load(bad)


def test_missing_file_is_an_oserror(tmp_path: Path) -> None:
    with pytest.raises(OSError, match="nope.npz"):
        lp3d_render.Triplane.load(tmp_path / "nope.npz")


def test_failed_save_writes_nothing(tmp_path: Path) -> None:
    tri = make_scene(size=(8, 8)).native
    with pytest.raises(OSError, match="no-such-dir"):
        tri.save(tmp_path / "no-such-dir" / "t.npz")
    target = tmp_path / "keep.npz"
    target.write_bytes(b"original")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        import os

        if os.geteuid() != 0:  # root ignores directory permissions
            with pytest.raises(OSError):
                tri.save(locked / "t.npz")
            assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o700)
    # Saving over a directory fails and leaves no temporary file behind.
    (tmp_path / "adir.npz").mkdir()
    with pytest.raises(OSError, match="adir.npz"):
        tri.save(tmp_path / "adir.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir.npz", "keep.npz", "locked"]
    assert target.read_bytes() == b"original"
