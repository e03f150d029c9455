"""lp3d_render's behaviour as a user meets it: shapes, output selection, determinism, batching,
file round trips across languages, and the conventions shared with the Python package."""

from __future__ import annotations

import dataclasses
import inspect
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import lp3d_render
from lp3d.render import camera as pycam
from lp3d.render import settings
from lp3d.render.triplane import PLANE_AXES
from lp3d.render.triplane_io import load_triplane, save_triplane
from support.scenes import PARITY_CAMERAS, make_scene

KW = {"resolution": 9, "depth_resolution": 12, "depth_resolution_importance": 12}


def test_adapter_info_names_a_device(gpu) -> None:
    assert set(gpu) >= {"backend", "name", "device_type", "driver"}
    assert gpu["name"]


def test_shapes_single_and_batch(gpu) -> None:
    scene = make_scene()
    one = lp3d_render.render(scene.native, PARITY_CAMERAS["frontal"], **KW)
    assert {k: v.shape for k, v in one.items()} == {
        "features": (32, 9, 9),
        "rgb": (3, 9, 9),
        "depth": (9, 9),
        "weights_sum": (9, 9),
    }
    cams = np.stack([PARITY_CAMERAS["frontal"], PARITY_CAMERAS["yaw+45"], PARITY_CAMERAS["rolled"]])
    batch = lp3d_render.render(scene.native, cams, **KW)
    assert batch["features"].shape == (3, 32, 9, 9) and batch["depth"].shape == (3, 9, 9)
    # Rendering a batch equals rendering each camera alone (deterministic mode: the batch-global
    # depth clamp is [ray_start, ray_end] for every batch).
    for i in range(3):
        alone = lp3d_render.render(scene.native, cams[i], **KW)
        for key in alone:
            np.testing.assert_array_equal(batch[key][i], alone[key])
    assert np.array_equal(batch["rgb"], batch["features"][:, :3])


def test_outputs_restrict_what_is_returned(gpu) -> None:
    scene = make_scene(decoder="strong")
    cam = PARITY_CAMERAS["pitch+25"]
    full = lp3d_render.render(scene.native, cam, **KW)
    for names in (["rgb"], ["depth"], ["weights_sum", "depth"], ["features"]):
        part = lp3d_render.render(scene.native, cam, outputs=names, **KW)
        assert set(part) == set(names)
        for key in names:
            # Fewer decoder rows are evaluated but the composited values are identical.
            np.testing.assert_array_equal(part[key], full[key])


def test_deterministic_by_default_and_seeded_jitter(gpu) -> None:
    scene = make_scene(decoder="strong")
    cam = PARITY_CAMERAS["frontal"]
    a = lp3d_render.render(scene.native, cam, **KW)
    b = lp3d_render.render(scene.native, cam, **KW)
    np.testing.assert_array_equal(a["features"], b["features"])
    j1 = lp3d_render.render(scene.native, cam, deterministic=False, seed=5, **KW)
    j2 = lp3d_render.render(scene.native, cam, deterministic=False, seed=5, **KW)
    j3 = lp3d_render.render(scene.native, cam, deterministic=False, seed=6, **KW)
    np.testing.assert_array_equal(j1["features"], j2["features"])
    assert np.abs(j1["features"] - j3["features"]).max() > 1e-4
    assert np.abs(j1["features"] - a["features"]).max() > 1e-4


def test_render_releases_the_gil(gpu) -> None:
    scene = make_scene()
    cams = np.stack([PARITY_CAMERAS["frontal"]] * 4)
    lp3d_render.render(scene.native, cams, **KW)  # warm up (pipeline compile)
    ticks = 0
    done = threading.Event()

    def count() -> None:
        nonlocal ticks
        while not done.is_set():
            ticks += 1
            time.sleep(0.001)

    t = threading.Thread(target=count)
    t.start()
    start = time.perf_counter()
    lp3d_render.render(scene.native, cams, resolution=48, depth_resolution=24, depth_resolution_importance=24)
    elapsed = time.perf_counter() - start
    done.set()
    t.join()
    # With the GIL held, the counter could not run at all while rendering.
    assert elapsed > 0.02 and ticks >= 5, (elapsed, ticks)


def test_file_round_trips_across_languages(gpu, tmp_path: Path) -> None:
    for dtype in (np.float32, np.float16):
        scene = make_scene(size=(16, 24), dtype=dtype)
        # Rust writes, Python reads.
        rust_file = tmp_path / f"rust-{np.dtype(dtype).name}.npz"
        scene.native.save(rust_file)
        back = load_triplane(rust_file)
        assert back.planes.dtype == dtype
        np.testing.assert_array_equal(back.planes, scene.data.planes)
        for name in ("w0", "b0", "w1", "b1"):
            np.testing.assert_array_equal(getattr(back, name), getattr(scene.data, name))
        # Python writes (with the optional keys), Rust reads.
        py_file = tmp_path / f"py-{np.dtype(dtype).name}.npz"
        cam = pycam.look_at_camera(yaw_deg=12.0)
        occ = scene.data.to_native().bake_occupancy(4)
        written = dataclasses.replace(
            scene.data,
            box_warp=1.2,
            ray_start=2.0,
            ray_end=3.5,
            camera=cam,
            occupancy=occ,
            source="unit test",
        )
        save_triplane(py_file, written)
        loaded = lp3d_render.Triplane.load(py_file)
        # TriplaneData.to_native hands the renderer the same triplane without a file.
        for tri in (loaded, written.to_native()):
            np.testing.assert_array_equal(tri.planes, scene.data.planes)
            assert tri.planes.dtype == dtype
            assert (tri.box_warp, tri.ray_start, tri.ray_end) == (
                np.float32(1.2),
                np.float32(2.0),
                np.float32(3.5),
            )
            np.testing.assert_allclose(tri.camera, cam, atol=1e-7)
            np.testing.assert_array_equal(tri.occupancy, occ)
            assert tri.source == "unit test"
        # And the Rust-loaded triplane renders exactly like the in-memory one.
        np.testing.assert_array_equal(
            lp3d_render.render(loaded, cam, **KW)["rgb"],
            lp3d_render.render(written.to_native(), cam, **KW)["rgb"],
        )


def test_settings_agree_across_languages() -> None:
    sig = inspect.signature(lp3d_render.render)
    defaults = settings.RenderSettings()
    # Every field of the Python settings (skips flattened) is a keyword of the native render, with the
    # same default, and native_kwargs() spells exactly those keywords.
    flat = {**dataclasses.asdict(defaults), **dataclasses.asdict(defaults.skips)}
    del flat["skips"], flat["seed"]  # the native seed defaults to None: a fresh one per jittered call
    for name, value in flat.items():
        assert sig.parameters[name].default == value, name
    assert set(defaults.native_kwargs()) == set(flat)
    assert lp3d_render.MAX_RESOLUTION == settings.MAX_RESOLUTION
    assert lp3d_render.MAX_SAMPLES == settings.MAX_SAMPLES
    assert [tuple(a) for a in lp3d_render.PLANE_AXES] == [tuple(a) for a in PLANE_AXES]
    # EG3D's FFHQ conventions: one name per language (Rust's module constants, Python's lp3d.render.camera
    # and lp3d.render.settings), and the native signatures' defaults spell those constants.
    scene = {
        name: getattr(settings, name) for name in ("DEFAULT_BOX_WARP", "DEFAULT_RAY_START", "DEFAULT_RAY_END")
    }
    ffhq = {"FFHQ_FOCAL": pycam.FFHQ_FOCAL, "FFHQ_RADIUS": pycam.FFHQ_RADIUS, "FFHQ_PIVOT": pycam.FFHQ_PIVOT}
    for name, value in {**scene, **ffhq}.items():
        assert getattr(lp3d_render, name) == value, name
    tri_sig = inspect.signature(lp3d_render.Triplane)
    assert tri_sig.parameters["box_warp"].default == lp3d_render.DEFAULT_BOX_WARP
    assert tri_sig.parameters["ray_start"].default == lp3d_render.DEFAULT_RAY_START
    assert tri_sig.parameters["ray_end"].default == lp3d_render.DEFAULT_RAY_END
    cam_sig = inspect.signature(lp3d_render.look_at_camera)
    assert cam_sig.parameters["radius"].default == lp3d_render.FFHQ_RADIUS
    assert cam_sig.parameters["focal"].default == lp3d_render.FFHQ_FOCAL
    assert cam_sig.parameters["lookat"].default == lp3d_render.FFHQ_PIVOT


@pytest.mark.parametrize(
    "angles",
    [
        {},
        {"yaw_deg": 30.0},
        {"yaw_deg": -50.0, "pitch_deg": 20.0},
        {"pitch_deg": -35.0, "roll_deg": 15.0},
        {"yaw_deg": 170.0, "radius": 1.5, "lookat": (0.1, -0.2, 0.3), "focal": 2.0},
    ],
)
def test_rust_orbit_camera_matches_python(angles: dict) -> None:
    rust = lp3d_render.look_at_camera(**angles)
    py = pycam.look_at_camera(**angles)
    np.testing.assert_allclose(rust, py, atol=2e-7)
