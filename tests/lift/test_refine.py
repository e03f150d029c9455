"""``lp3d.lift.refine``: fitting a lifted head to its photo.

Everything here is CPU torch on the hand-built coloured sphere at 32² planes, 24² rays and 8+8
samples, so it runs in seconds. The refinement's measured effect on held-out teacher identities
is ``lp3d eval --refine`` (``docs/performance.md``, "Held-out evaluation"), not these tests."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lp3d.lift.pose import camera_at, estimate_pose, fit_pose, moved_camera
from lp3d.lift.refine import RefineSettings, refine
from lp3d.render.camera import camera_summary, look_at_camera
from lp3d.render.psnr import psnr_db
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.torch_twin import render_torch

SMALL = RefineSettings(
    steps=40,
    lr=0.05,
    prior_weight=0.0,
    resolution=24,
    rays_per_step=288,
    depth_resolution=8,
    depth_resolution_importance=8,
    search_resolution=24,
)


def _weights(tri):
    return [torch.from_numpy(np.asarray(getattr(tri, k), np.float32)) for k in ("w0", "b0", "w1", "b1")]


def _photo(tri, yaw: float, pitch: float, resolution: int = 24, **camera) -> np.ndarray:
    """The truth's raw RGB (3, R, R) in [-1, 1] from (yaw, pitch) (and other ``look_at_camera``
    arguments): the "photo" a refinement fits."""
    planes = torch.from_numpy(np.asarray(tri.planes, np.float32))
    cam = torch.from_numpy(look_at_camera(yaw_deg=yaw, pitch_deg=pitch, **camera)).float()
    out = render_torch(
        planes, *_weights(tri), cam, resolution=resolution, depth_resolution=8, depth_resolution_importance=8
    )
    return out["rgb"].numpy()


@pytest.fixture(scope="module")
def scene():
    truth = coloured_sphere(size=32)
    rng = np.random.default_rng(0)
    # The "encoder's guess": the truth with its colour planes washed out and noise everywhere.
    planes = np.asarray(truth.planes, np.float32).copy()
    planes[:, 1:4] *= 0.3
    planes += rng.normal(0, 0.3, planes.shape).astype(np.float32)
    guess = dataclasses.replace(truth, planes=planes, source="test guess")
    return truth, guess, _photo(truth, 20.0, 0.0)


def test_refinement_fits_the_input_view_and_leaves_its_input_alone(scene) -> None:
    truth, guess, photo = scene
    before = guess.planes.copy()
    result = refine(guess, photo, SMALL, pose=(20.0, 0.0))
    np.testing.assert_array_equal(guess.planes, before)
    assert result.psnr_after > result.psnr_before + 3.0, (result.psnr_before, result.psnr_after)
    # The reported PSNR is the refined triplane's own render of the input view.
    again = psnr_db(_photo(result.triplane, 20.0, 0.0), photo)
    assert again == pytest.approx(result.psnr_after, abs=0.05)
    tri = result.triplane
    assert tri.planes.shape == guess.planes.shape and tri.planes.dtype == guess.planes.dtype
    np.testing.assert_array_equal(tri.w0, guess.w0)  # the decoder is the package's: never fitted
    assert tri.bounds == guess.bounds and "refined 40 steps" in tri.source
    np.testing.assert_allclose(tri.camera, look_at_camera(yaw_deg=20.0, pitch_deg=0.0))


def test_the_prior_holds_the_planes_at_the_encoders_output(scene) -> None:
    _, guess, photo = scene
    free = refine(guess, photo, SMALL, pose=(20.0, 0.0)).triplane.planes - guess.planes
    held = (
        refine(guess, photo, dataclasses.replace(SMALL, prior_weight=1e4), pose=(20.0, 0.0)).triplane.planes
        - guess.planes
    )
    assert np.abs(held).mean() < 0.1 * np.abs(free).mean()


def test_the_occupancy_grid_of_the_old_planes_is_not_kept(scene) -> None:
    """A baked grid bounds the encoder's planes' density; the refined planes may exceed it."""
    _, guess, photo = scene
    baked = dataclasses.replace(guess, occupancy=np.ones((4, 4, 4), np.float32))
    result = refine(baked, photo, dataclasses.replace(SMALL, steps=1), pose=(0.0, 0.0))
    assert result.triplane.occupancy is None


def test_zero_steps_is_the_encoders_triplane(scene) -> None:
    _, guess, photo = scene
    result = refine(guess, photo, dataclasses.replace(SMALL, steps=0), pose=(0.0, 0.0))
    np.testing.assert_array_equal(result.triplane.planes, guess.planes)
    assert result.psnr_after == result.psnr_before


def test_the_pose_search_finds_the_view_of_the_photo() -> None:
    truth = coloured_sphere(size=32)
    planes = torch.from_numpy(np.asarray(truth.planes, np.float32))
    for yaw, pitch in ((20.0, 0.0), (-30.0, 10.0)):
        found = estimate_pose(planes, tuple(_weights(truth)), truth.bounds, _photo(truth, yaw, pitch), SMALL)
        assert found == (yaw, pitch)


def test_a_uint8_crop_is_the_same_photo_as_its_float_image(scene) -> None:
    _, guess, photo = scene
    crop = np.round((np.clip(photo, -1, 1) + 1) * 127.5).astype(np.uint8).transpose(1, 2, 0)
    a = refine(guess, crop, dataclasses.replace(SMALL, steps=2), pose=(20.0, 0.0))
    b = refine(
        guess, crop.transpose(2, 0, 1) / 127.5 - 1.0, dataclasses.replace(SMALL, steps=2), pose=(20.0, 0.0)
    )
    np.testing.assert_allclose(a.triplane.planes, b.triplane.planes, atol=1e-6)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"steps": -1}, "steps"),
        ({"steps": 10**6}, "steps"),
        ({"lr": float("nan")}, "lr"),
        ({"prior_weight": -1.0}, "prior_weight"),
        ({"resolution": 4}, "resolution"),
        ({"search_yaws_deg": ()}, "search_yaws_deg"),
        ({"search_pitches_deg": (95.0,)}, "search_pitches_deg"),
        ({"steps": True}, "steps"),
        ({"superres_share": 1.5}, "superres_share"),
        ({"superres_lr": -0.1}, "superres_lr"),
        ({"superres_samples": (2, 8)}, "superres_samples"),
    ],
)
def test_bad_settings_name_the_field(change, field) -> None:
    with pytest.raises(ValueError, match=f"RefineSettings.{field} "):
        RefineSettings(**change)


@pytest.mark.parametrize(
    "image, what",
    [
        (np.zeros((3, 24, 20), np.float32), "shape"),
        (np.zeros((24, 24), np.float32), "shape"),
        (np.full((3, 24, 24), np.nan, np.float32), "NaN"),
    ],
)
def test_bad_photos_are_refused(scene, image, what) -> None:
    _, guess, _ = scene
    with pytest.raises(ValueError, match=what):
        refine(guess, image, SMALL, pose=(0.0, 0.0))


def test_a_moved_camera_is_the_camera_when_nothing_moves_and_an_orbit_when_it_turns() -> None:
    start = torch.from_numpy(look_at_camera(yaw_deg=10.0, pitch_deg=5.0))
    np.testing.assert_array_equal(
        moved_camera(start, torch.zeros(6, dtype=torch.float64)).numpy(), start.numpy()
    )
    # A turn about the world's +y axis is a change of yaw: the centre orbits, the camera stays a camera.
    turned = moved_camera(
        start, torch.tensor([0.0, np.radians(7.0), 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    )
    a, b = camera_summary(start.numpy()), camera_summary(turned.numpy())
    assert b["yaw_deg"] == pytest.approx(a["yaw_deg"] + 7.0, abs=1e-9)
    assert b["pitch_deg"] == pytest.approx(a["pitch_deg"], abs=1e-9)
    rot = turned[:16].reshape(4, 4)[:3, :3].numpy()
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    # Principal point and focal length move as documented.
    k = moved_camera(start, torch.tensor([0, 0, 0, 0.02, -0.01, np.log(1.1)], dtype=torch.float64))[16:]
    np.testing.assert_allclose(
        k.numpy()[[0, 2, 4, 5]], [start[16] * 1.1, start[18] + 0.02, start[20] * 1.1, start[21] - 0.01]
    )
    # Its gradient is finite at zero, where the rotation's series take over.
    delta = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    moved_camera(start, delta).square().sum().backward()
    assert delta.grad is not None and bool(torch.isfinite(delta.grad).all())


def test_the_pose_fit_finds_a_camera_off_the_grid() -> None:
    """A photo from yaw 27°, pitch 4°, a longer lens and a shifted crop: the grid camera is several
    degrees off; the fit, with the truth's own planes, comes back close to the truth."""
    truth = coloured_sphere(size=32)
    planes = torch.from_numpy(np.asarray(truth.planes, np.float32))
    photo = _photo(truth, 27.0, 4.0, focal=4.6, cx=0.52)
    start = camera_at(30.0, 0.0)
    settings = dataclasses.replace(SMALL, pose_steps=60, pose_lr=0.02, pose_resolution=24)
    found = fit_pose(planes, tuple(_weights(truth)), truth.bounds, photo, start, settings)
    s = camera_summary(found.double().numpy())
    assert abs(s["yaw_deg"] - 27.0) < 1.0 and abs(s["pitch_deg"] - 4.0) < 1.0, s
    assert s["focal"] == pytest.approx(4.6, rel=0.03)


def test_refine_finds_the_camera_when_none_is_given() -> None:
    truth = coloured_sphere(size=32)
    photo = _photo(truth, 23.0, 3.0)
    steps = []
    settings = dataclasses.replace(SMALL, steps=2, pose_steps=30)
    result = refine(truth, photo, settings, on_step=lambda: steps.append(1))
    assert len(steps) == settings.total_steps() == 32  # the pose's steps, then the planes'
    assert abs(result.yaw_deg - 23.0) < 1.0 and abs(result.pitch_deg - 3.0) < 1.0, result
    np.testing.assert_array_equal(result.triplane.camera, result.camera)
    # A video's next frame starts from the last camera: no grid search, the pose steps only.
    steps.clear()
    start = look_at_camera(yaw_deg=26.0, pitch_deg=3.0)
    again = refine(truth, photo, settings, start_camera=start, on_step=lambda: steps.append(1))
    assert len(steps) == 32 and abs(again.yaw_deg - 23.0) < 1.0, again
    with pytest.raises(ValueError, match="start_camera"):
        refine(truth, photo, SMALL, start_camera=np.stack([start] * 2))


def test_fit_camera_moves_a_camera_given_off_toward_the_photos(scene) -> None:
    """With ``fit_camera``, the raw steps move the camera with the planes: started 6° off in yaw (the
    planes the truth's, held by the prior), the refine ends near the photo's camera, and the label
    it returns is the moved one; without it the given camera stays as it is. A whole camera label
    is taken as it is too."""
    truth, _, _ = scene
    guess = truth
    photo = _photo(truth, 26.0, 0.0)
    settings = dataclasses.replace(SMALL, steps=60, prior_weight=1.0, fit_camera=True, pose_lr=0.02)
    moved = refine(guess, photo, settings, pose=(20.0, 0.0))
    held = refine(guess, photo, dataclasses.replace(settings, fit_camera=False), pose=(20.0, 0.0))
    assert abs(moved.yaw_deg - 26.0) < 1.5 and abs(moved.pitch_deg) < 1.5, (moved.yaw_deg, moved.pitch_deg)
    np.testing.assert_allclose(held.camera, look_at_camera(yaw_deg=20.0, pitch_deg=0.0), atol=1e-6)
    np.testing.assert_array_equal(moved.triplane.camera, moved.camera)
    label = look_at_camera(yaw_deg=20.0, pitch_deg=0.0)
    same = refine(guess, photo, dataclasses.replace(settings, fit_camera=False), camera=label)
    np.testing.assert_array_equal(same.triplane.planes, held.triplane.planes)
    with pytest.raises(ValueError, match="pose or camera, not both"):
        refine(guess, photo, settings, pose=(20.0, 0.0), camera=label)


def test_refine_is_reproducible_on_two_threads(scene) -> None:
    """The same photo refined twice gives the same camera and planes, bit for bit, with torch's two
    CPU threads. The triplane lookup's backward once summed the two planes sharing a world axis in
    thread order (an accumulating index_put_), so two runs of `lp3d encode --refine` differed (camera
    by up to 0.06, planes by 0.2 on a teacher head)."""
    _, guess, photo = scene
    settings = dataclasses.replace(SMALL, steps=10, pose_steps=20)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        runs = [refine(guess, photo, settings) for _ in range(3)]
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        np.testing.assert_array_equal(other.camera, runs[0].camera)
        np.testing.assert_array_equal(other.triplane.planes, runs[0].triplane.planes)


def test_the_super_resolved_steps_fit_the_image_the_network_makes() -> None:
    """With an SR network, the last steps fit its image at the network's side (here 2x the feature
    image's): the refined head's super-resolved render is nearer the photo than the raw fit alone
    makes it, and the step split follows ``superres_share``."""
    from lp3d.lift.refine import refine_planes
    from lp3d.nets.superres import FoldedSuperResolution, SuperresConfig, SuperResolution
    from lp3d.render.torch_stages import rays_from_cameras
    from lp3d.render.torch_twin import render_rays

    torch.manual_seed(0)
    sr = SuperResolution(
        SuperresConfig(name="t", input_resolution=16, output_resolution=32, block_channels=(8,), w_dim=8)
    )
    net = FoldedSuperResolution(sr).eval()
    truth = coloured_sphere(size=16)
    planes = torch.from_numpy(np.asarray(truth.planes, np.float32))
    dec = tuple(_weights(truth))
    cam = camera_at(0.0, 0.0)
    photo = torch.from_numpy(np.random.default_rng(1).uniform(-1, 1, (3, 32, 32)).astype(np.float32))
    settings = dataclasses.replace(SMALL, steps=12, resolution=16, superres_samples=(6, 6), mirror=False)
    assert settings.superres_steps(True) == 8 and settings.superres_steps(False) == 0

    def sr_error(p: torch.Tensor) -> float:
        o, d = rays_from_cameras(cam[None], 16)
        rs = settings.render_settings(16, settings.superres_samples)
        with torch.no_grad():
            f = render_rays(p[None], *dec, o, d, bounds=truth.bounds, settings=rs, clamp=False)["features"]
            return float((net(f.transpose(1, 2).reshape(1, -1, 16, 16))[0] - photo).abs().mean())

    raw_only, _ = refine_planes(planes, dec, truth.bounds, photo.numpy(), cam, settings)
    with_sr, _ = refine_planes(planes, dec, truth.bounds, photo.numpy(), cam, settings, superres=net)
    assert sr_error(with_sr) < sr_error(raw_only) - 0.01, (sr_error(with_sr), sr_error(raw_only))
