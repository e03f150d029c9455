"""The training camera distributions (paper §3.2, supplement "Camera augmentation").

Moments are checked on large samples (N = 200000 parameter draws; tolerances of about 5 standard
errors for means, 1-2% for spreads), and on 2000 full labels the sampled parameters are recovered with
geometry written out here, so a label that disagrees with its parameters fails.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lp3d.render.camera import FFHQ_FOCAL, FFHQ_PIVOT, fov_to_focal, validate_camera
from lp3d.training.camera_sampling import (
    AFHQ_REFERENCE,
    FFHQ_MULTIVIEW,
    FFHQ_REFERENCE,
    CameraDistribution,
    sample_cameras,
)

N = 200_000
N_LABELS = 2_000


@pytest.fixture(scope="module")
def reference():
    return sample_cameras(FFHQ_REFERENCE, N, np.random.default_rng(0), labels=False)


@pytest.fixture(scope="module")
def multiview():
    return sample_cameras(FFHQ_MULTIVIEW, N, np.random.default_rng(1), labels=False)


@pytest.fixture(scope="module")
def reference_labelled():
    return sample_cameras(FFHQ_REFERENCE, N_LABELS, np.random.default_rng(5))


def _recover(labels: np.ndarray) -> dict[str, np.ndarray]:
    """Yaw, pitch, radius (camera centre), roll (camera right axis vs the level right axis),
    focal and principal point, from labels (B, 25)."""
    c2w = labels[:, :16].reshape(-1, 4, 4)
    k = labels[:, 16:].reshape(-1, 3, 3)
    centre = c2w[:, :3, 3]
    radius = np.linalg.norm(centre, axis=1)
    yaw = np.degrees(np.arctan2(centre[:, 0], centre[:, 2]))
    pitch = np.degrees(np.arcsin(centre[:, 1] / radius))
    right, forward = c2w[:, :3, 0], c2w[:, :3, 2]
    level_right = -np.cross(np.array([0.0, 1.0, 0.0]), forward)
    level_right /= np.linalg.norm(level_right, axis=1, keepdims=True)
    level_down = np.cross(forward, level_right)
    roll = np.degrees(np.arctan2((right * level_down).sum(1), (right * level_right).sum(1)))
    return {
        "radius": radius,
        "yaw": yaw,
        "pitch": pitch,
        "roll": roll,
        "forward": forward,
        "centre": centre,
        "fx": k[:, 0, 0],
        "fy": k[:, 1, 1],
        "cx": k[:, 0, 2],
        "cy": k[:, 1, 2],
    }


def test_labels_are_valid_cameras_that_match_their_parameters(reference_labelled):
    reference = reference_labelled
    cams, batched = validate_camera(reference.labels)
    assert batched and cams.shape == (N_LABELS, 25)
    got = _recover(reference.labels)
    np.testing.assert_allclose(got["radius"], reference.radius, atol=1e-9)
    np.testing.assert_allclose(got["yaw"], reference.yaw_deg, atol=1e-6)
    np.testing.assert_allclose(got["pitch"], reference.pitch_deg, atol=1e-6)
    np.testing.assert_allclose(got["roll"], reference.roll_deg, atol=1e-6)
    np.testing.assert_allclose(got["fx"], reference.focal)
    np.testing.assert_allclose(got["fy"], reference.focal)
    np.testing.assert_allclose(got["cx"], reference.cx)
    np.testing.assert_allclose(got["cy"], reference.cy)
    # Every camera looks at the FFHQ pivot.
    to_pivot = np.asarray(FFHQ_PIVOT) - got["centre"]
    to_pivot /= np.linalg.norm(to_pivot, axis=1, keepdims=True)
    np.testing.assert_allclose((to_pivot * got["forward"]).sum(1), 1.0, atol=1e-9)


def test_reference_pose_is_uniform_within_the_paper_ranges(reference):
    # Uniform on [-a, a]: mean 0 (SE a/sqrt(3N)), std a/sqrt(3), a quarter of the mass in each half-half.
    for values, a in ((reference.yaw_deg, 49.0), (reference.pitch_deg, 26.0)):
        assert values.min() >= -a and values.max() <= a
        assert values.min() < -0.99 * a and values.max() > 0.99 * a  # the limits are reached
        assert abs(values.mean()) < 5 * a / math.sqrt(3 * N)
        assert values.std() == pytest.approx(a / math.sqrt(3), rel=0.01)
        assert np.mean(np.abs(values) < a / 2) == pytest.approx(0.5, abs=0.01)


def test_reference_intrinsics_radius_and_roll_follow_the_supplement(reference):
    fov = reference.fov_deg
    assert fov.mean() == pytest.approx(18.83, abs=5 * 1.0 / math.sqrt(N))
    assert fov.std() == pytest.approx(1.0, rel=0.01)
    np.testing.assert_allclose(reference.focal[:500], [fov_to_focal(f) for f in fov[:500]])
    # The mean focal length is EG3D's FFHQ focal length (18.83 EG3D-degrees ~ 4.2647).
    assert np.median(reference.focal) == pytest.approx(FFHQ_FOCAL, rel=0.005)
    assert reference.radius.mean() == pytest.approx(2.7, abs=5 * 0.1 / math.sqrt(N))
    assert reference.radius.std() == pytest.approx(0.1, rel=0.01)
    for c in (reference.cx, reference.cy):  # N(256, 14) px of 512, normalised
        assert c.mean() == pytest.approx(0.5, abs=5 * (14 / 512) / math.sqrt(N))
        assert c.std() == pytest.approx(14 / 512, rel=0.01)
    assert np.corrcoef(reference.cx, reference.cy)[0, 1] == pytest.approx(0.0, abs=0.01)
    assert reference.roll_deg.mean() == pytest.approx(0.0, abs=5 * 2.0 / math.sqrt(N))
    assert reference.roll_deg.std() == pytest.approx(2.0, rel=0.01)


def test_multiview_cameras_are_fixed_ffhq_cameras_within_the_pose_range(multiview):
    assert np.all(multiview.focal == FFHQ_FOCAL)
    assert np.all(multiview.cx == 0.5) and np.all(multiview.cy == 0.5)
    assert np.all(multiview.radius == 2.7)
    assert np.all(multiview.roll_deg == 0.0)
    labelled = sample_cameras(FFHQ_MULTIVIEW, 500, np.random.default_rng(1))
    np.testing.assert_array_equal(labelled.yaw_deg, multiview.yaw_deg[:500])  # same draws with labels
    got = _recover(labelled.labels)
    np.testing.assert_allclose(got["roll"], 0.0, atol=1e-9)
    np.testing.assert_allclose(got["radius"], 2.7, atol=1e-12)
    for values, a in ((multiview.yaw_deg, 36.0), (multiview.pitch_deg, 26.0)):
        assert -a <= values.min() < -0.99 * a and 0.99 * a < values.max() <= a
        assert values.std() == pytest.approx(a / math.sqrt(3), rel=0.02)


def test_afhq_preset_has_the_wider_spreads():
    s = sample_cameras(AFHQ_REFERENCE, N, np.random.default_rng(2), labels=False)
    assert s.fov_deg.std() == pytest.approx(1.5, rel=0.01)
    assert s.cx.std() == pytest.approx(25 / 512, rel=0.01)
    assert s.roll_deg.std() == pytest.approx(6.0, rel=0.01)


def test_same_generator_state_gives_the_same_cameras_for_numpy_and_torch():
    a = sample_cameras(FFHQ_REFERENCE, 64, np.random.default_rng(7)).labels
    b = sample_cameras(FFHQ_REFERENCE, 64, np.random.default_rng(7)).labels
    np.testing.assert_array_equal(a, b)
    ta = sample_cameras(FFHQ_REFERENCE, 64, torch.Generator().manual_seed(7))
    tb = sample_cameras(FFHQ_REFERENCE, 64, torch.Generator().manual_seed(7))
    np.testing.assert_array_equal(ta.labels, tb.labels)
    assert not np.array_equal(ta.labels, a)
    big = sample_cameras(FFHQ_MULTIVIEW, N, torch.Generator().manual_seed(3), labels=False)
    assert big.yaw_deg.std() == pytest.approx(36 / math.sqrt(3), rel=0.01)
    assert big.labels is None


def test_bad_arguments_are_clear_errors():
    with pytest.raises(ValueError, match="n must be a positive int"):
        sample_cameras(FFHQ_REFERENCE, 0, np.random.default_rng(0))
    with pytest.raises(TypeError, match="Generator"):
        sample_cameras(FFHQ_REFERENCE, 4, 123)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="radius_std"):
        CameraDistribution(radius_std=-1.0)
    with pytest.raises(ValueError, match="pitch_range_deg"):
        CameraDistribution(pitch_range_deg=90.0)


def test_distribution_json_round_trip():
    d = FFHQ_MULTIVIEW.to_dict()
    assert CameraDistribution.from_dict(d) == FFHQ_MULTIVIEW
    with pytest.raises(ValueError, match="unknown keys"):
        CameraDistribution.from_dict({**d, "zoom": 2})
