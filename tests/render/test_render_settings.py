"""One RenderSettings and one SceneBounds for the three renderers (lp3d.render.settings).

The float64 reference, the torch twin and the GPU renderer take the same settings object, keyword
overrides of its fields, and the scene bounds of the triplane; each refuses what it cannot do. Parity
tolerances are the renderers' usual ones (tests/render/test_render_parity.py): 1e-4 on features and depth for
the float32 paths against the float64 reference."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import lp3d_render
from lp3d.lift.inference import DEFAULT_MODEL
from lp3d.lift.model_package import ModelPackageError, load_model_package
from lp3d.render import native
from lp3d.render.camera import look_at_camera, stack_labels
from lp3d.render.reference import render_reference
from lp3d.render.settings import RenderSettings, SceneBounds, Skips, resolve_settings
from lp3d.render.torch_twin import render_with_twin
from lp3d.render.triplane import TriplaneError
from lp3d.render.triplane_io import load_triplane, save_triplane
from support.scenes import make_scene

TOL = 1e-4
CAMERAS = stack_labels([look_at_camera(yaw_deg=20.0), look_at_camera(pitch_deg=-10.0)])
SMALL = RenderSettings(resolution=8, depth_resolution=8, depth_resolution_importance=8)


def render_all(tri, settings: RenderSettings) -> dict[str, dict[str, np.ndarray]]:
    return {
        "reference": render_reference(tri, CAMERAS, settings),
        "torch": render_with_twin(tri, CAMERAS, settings),
        "native": native.render(tri, CAMERAS, settings),
    }


@pytest.mark.parametrize(
    "settings",
    [SMALL, dataclasses.replace(SMALL, deterministic=False, seed=7, white_back=True)],
    ids=["deterministic", "jittered-white"],
)
def test_one_settings_object_renders_alike_in_all_three(gpu, settings: RenderSettings) -> None:
    tri = make_scene(size=(16, 16), seed=3).data
    out = render_all(tri, settings)
    ref = out["reference"]
    assert ref["rgb"].shape == (2, 3, 8, 8)
    for name in ("torch", "native"):
        for key in ("features", "depth"):
            err = float(np.abs(out[name][key].astype(np.float64) - ref[key]).max())
            assert err <= TOL, f"{name} {key}: {err:.2e}"


def test_keyword_overrides_are_the_settings_fields(gpu) -> None:
    tri = make_scene(size=(16, 16), seed=4).data
    kw = {"resolution": 8, "depth_resolution": 8, "depth_resolution_importance": 8}
    np.testing.assert_array_equal(
        render_reference(tri, CAMERAS, **kw)["rgb"], render_all(tri, SMALL)["reference"]["rgb"]
    )
    np.testing.assert_array_equal(
        render_with_twin(tri, CAMERAS, RenderSettings(), **kw)["rgb"],
        render_with_twin(tri, CAMERAS, SMALL)["rgb"],
    )
    np.testing.assert_array_equal(
        native.render(tri, CAMERAS, **kw)["rgb"],
        lp3d_render.render(tri.to_native(), CAMERAS, **kw)["rgb"],
    )
    for render in (render_reference, render_with_twin, native.render):
        with pytest.raises(TypeError, match="depth_samples"):
            render(tri, CAMERAS, SMALL, depth_samples=8)


def test_skips_reach_the_gpu_and_are_refused_by_the_exact_renderers(gpu) -> None:
    tri = make_scene(size=(16, 16), seed=5).data
    skips = Skips(transmittance_threshold=0.01, empty_threshold=0.001)
    skipping = dataclasses.replace(SMALL, skips=skips)
    flat = {**dataclasses.asdict(SMALL), **dataclasses.asdict(skips)}
    del flat["skips"], flat["seed"]
    np.testing.assert_array_equal(
        native.render(tri, CAMERAS, skipping)["rgb"],
        lp3d_render.render(tri.to_native(), CAMERAS, **flat)["rgb"],
    )
    for render in (render_reference, render_with_twin):
        with pytest.raises(ValueError, match="exact EG3D semantics: skips"):
            render(tri, CAMERAS, skipping)


def test_bounds_come_from_the_triplane_and_can_be_overridden() -> None:
    tri = make_scene(size=(16, 16), seed=6).data
    bounds = SceneBounds(box_warp=1.2, ray_start=2.0, ray_end=3.5)
    moved = dataclasses.replace(tri, **dataclasses.asdict(bounds))
    assert moved.bounds == bounds and SceneBounds.of(moved) == bounds
    want = render_reference(moved, CAMERAS, SMALL)["rgb"]
    np.testing.assert_array_equal(
        render_reference(tri, CAMERAS, SMALL, **dataclasses.asdict(bounds))["rgb"], want
    )
    got = render_with_twin(tri, CAMERAS, SMALL, box_warp=1.2, ray_start=2.0, ray_end=3.5)["rgb"]
    assert float(np.abs(got - want).max()) <= TOL
    with pytest.raises(TypeError, match="scene bounds from the triplane"):
        native.render(tri, CAMERAS, SMALL, ray_start=2.0)


@pytest.mark.parametrize(
    ("bounds", "field", "words"),
    [
        (SceneBounds(box_warp=0.0), "box_warp", "> 0"),
        (SceneBounds(box_warp=float("nan")), "box_warp", "finite"),
        (SceneBounds(ray_start=-1.0), "ray_start", ">= 0"),
        (SceneBounds(ray_start=3.0, ray_end=2.0), "ray_end", "> ray_start"),
        (SceneBounds(ray_end=1e300), "ray_end", "not finite as float32"),
        (SceneBounds(ray_start=1.0, ray_end=1.0 + 1e-12), "ray_end", "also as float32"),
        (SceneBounds(box_warp="1"), "box_warp", "real number"),  # type: ignore[arg-type]
    ],
)
def test_scene_bounds_name_the_bad_field_everywhere(
    tmp_path, bounds: SceneBounds, field: str, words: str
) -> None:
    assert bounds.problem() is not None and bounds.problem()[0] == field and words in bounds.problem()[1]
    with pytest.raises(ValueError, match=f"^{field}: .*{words}"):
        bounds.validate()
    tri = make_scene(size=(4, 4)).data
    if not isinstance(bounds.box_warp, str):
        with pytest.raises(TriplaneError, match=field) as caught:
            dataclasses.replace(tri, **dataclasses.asdict(bounds))
        assert caught.value.field == field
        # A model package's sidecar runs the same check (the shipped one, its bounds replaced).
        sidecar = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
        sidecar.pop("superres", None)
        sidecar.update(dataclasses.asdict(bounds))
        (tmp_path / "bad.json").write_text(json.dumps(sidecar))
        with pytest.raises(ModelPackageError, match=f"bad.json: {field} .*{words}"):
            load_model_package(tmp_path / "bad.json")


def test_scene_bounds_of_every_holder(tmp_path) -> None:
    tri = make_scene(size=(4, 4), ray_start=2.0, ray_end=3.0, box_warp=0.9).data
    want = SceneBounds(box_warp=0.9, ray_start=2.0, ray_end=3.0)
    path = tmp_path / "t.npz"
    save_triplane(path, tri)
    holders = [tri, load_triplane(path), lp3d_render.Triplane.load(str(path)), dataclasses.asdict(want)]
    for holder in holders:  # the native handle holds float32 values
        np.testing.assert_allclose(
            dataclasses.astuple(SceneBounds.of(holder)), dataclasses.astuple(want), rtol=1e-7
        )
    assert SceneBounds() == SceneBounds.of(make_scene(size=(4, 4)).data)


def test_resolve_settings_validates_both() -> None:
    s, b = resolve_settings(None, {"resolution": 16, "ray_end": np.float32(3.5)})
    assert s == RenderSettings(resolution=16) and b == SceneBounds(ray_end=3.5) and type(b.ray_end) is float
    with pytest.raises(ValueError, match="resolution"):
        resolve_settings(None, {"resolution": 0})
    with pytest.raises(ValueError, match="ray_start"):
        resolve_settings(None, {"ray_start": -1.0})
    with pytest.raises(ValueError, match="occupancy_coarse needs"):
        RenderSettings(skips=Skips(occupancy_coarse=True)).validate()
    with pytest.raises(ValueError, match="resolution must be an int"):
        RenderSettings(resolution=True).validate()  # type: ignore[arg-type]
