"""lp3d.render.camera: EG3D's camera label, look-at poses and their sign conventions, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lp3d.render.camera import (
    FFHQ_FOCAL,
    FFHQ_PIVOT,
    FFHQ_RADIUS,
    eg3d_angles,
    focal_to_fov,
    fov_to_focal,
    intrinsics,
    look_at_cam2world,
    look_at_camera,
    lookat_pose,
    pack_label,
    stack_labels,
    unpack_label,
    validate_camera,
    yaw_pitch_from_eg3d_angles,
)


def _project(label: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """Normalised image coordinates (x right, y down, in [0, 1] on screen) of a world point."""
    c2w, K = unpack_label(label)
    p_cam = c2w[:3, :3].T @ (np.asarray(point, float) - c2w[:3, 3])
    assert p_cam[2] > 0, "point is behind the camera"
    xy = K @ (p_cam / p_cam[2])
    return float(xy[0]), float(xy[1])


def test_frontal_pose_matches_eg3d_sanity_numbers() -> None:
    # docs/eg3d-rendering.md §13: h = v = pi/2, radius 2.7, lookat origin (EG3D's float32 residues < 1e-6).
    c2w = lookat_pose(math.pi / 2, math.pi / 2, radius=2.7, lookat=(0, 0, 0))
    expected = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2.7], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(c2w, expected, atol=1e-6)
    # Columns are (right, down, forward): camera +y is world -y (OpenCV down in a y-up world).
    np.testing.assert_allclose(c2w[:3, 1], [0, -1, 0], atol=1e-12)


def test_frontal_look_at_camera_label() -> None:
    label = look_at_camera()
    assert label.shape == (25,) and label.dtype == np.float64
    c2w, K = unpack_label(label)
    np.testing.assert_allclose(c2w[:3, 3], [0, 0, FFHQ_RADIUS], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 2], [0, 0, -1], atol=1e-12)  # looks at the pivot (0, 0, 0.2)
    np.testing.assert_allclose(K, [[4.2647, 0, 0.5], [0, 4.2647, 0.5], [0, 0, 1]])
    assert FFHQ_FOCAL == 4.2647 and tuple(FFHQ_PIVOT) == (0, 0, 0.2)


def test_fov_to_focal_keeps_eg3d_quirks() -> None:
    assert fov_to_focal(18.837) == pytest.approx(4.2634, abs=1e-4)
    assert fov_to_focal(18) == pytest.approx(4.4652, abs=1e-4)  # gen_samples.py's int-truncated default
    # The quirky constants: not 1 / (2 tan(fov/2)).
    assert fov_to_focal(18.837) != pytest.approx(0.5 / math.tan(math.radians(18.837) / 2), rel=1e-3)
    assert fov_to_focal(18.837) == 1.0 / (math.tan(18.837 * 3.14159 / 360) * 1.414)


@pytest.mark.parametrize("fov", [1.0, 12.0, 18.837, 45.0, 90.0, 170.0])
def test_fov_focal_round_trip(fov: float) -> None:
    assert focal_to_fov(fov_to_focal(fov)) == pytest.approx(fov, rel=1e-12)
    assert fov_to_focal(focal_to_fov(4.2647)) == pytest.approx(4.2647, rel=1e-12)


@pytest.mark.parametrize("bad", [0.0, -3.0, 180.0, float("nan"), float("inf")])
def test_fov_to_focal_rejects_bad_values(bad: float) -> None:
    with pytest.raises(ValueError, match="fov"):
        fov_to_focal(bad)


def test_intrinsics_layout() -> None:
    np.testing.assert_array_equal(
        intrinsics(2.0, cx=0.4, cy=0.6, skew=0.1), [[2, 0.1, 0.4], [0, 2, 0.6], [0, 0, 1]]
    )


def test_yaw_positive_moves_camera_toward_plus_x() -> None:
    c2w, _ = unpack_label(look_at_camera(yaw_deg=30.0))
    r = FFHQ_RADIUS
    np.testing.assert_allclose(
        c2w[:3, 3], [r * math.sin(math.radians(30)), 0, r * math.cos(math.radians(30))], atol=1e-12
    )
    # EG3D's raw angle: larger h moves the camera toward +x too (h = pi/2 + yaw).
    assert lookat_pose(math.pi / 2 + 0.3, math.pi / 2)[0, 3] > 0
    np.testing.assert_allclose(
        c2w, lookat_pose(math.pi / 2 + math.radians(30), math.pi / 2, radius=r, lookat=FFHQ_PIVOT), atol=1e-12
    )


def test_pitch_positive_puts_camera_above_looking_down() -> None:
    c2w, _ = unpack_label(look_at_camera(pitch_deg=20.0))
    r, p = FFHQ_RADIUS, math.radians(20)
    np.testing.assert_allclose(c2w[:3, 3], [0, r * math.sin(p), r * math.cos(p)], atol=1e-12)
    assert c2w[1, 2] < 0  # forward has a downward (world -y) component
    # Smaller EG3D v also means higher; the mapping is v = pi/2 (1 - sin(pitch)).
    h, v = eg3d_angles(0.0, 20.0)
    assert h == pytest.approx(math.pi / 2) and v == pytest.approx(math.pi / 2 * (1 - math.sin(p)))
    assert v < math.pi / 2
    np.testing.assert_allclose(c2w, lookat_pose(h, v, radius=r, lookat=FFHQ_PIVOT), atol=1e-12)
    assert yaw_pitch_from_eg3d_angles(h, v) == pytest.approx((0.0, 20.0))


def test_yaw_and_pitch_together_and_radius() -> None:
    c2w, _ = unpack_label(look_at_camera(yaw_deg=-40.0, pitch_deg=-15.0, radius=3.0, lookat=(0, 0, 0)))
    y, p = math.radians(-40), math.radians(-15)
    expected = 3.0 * np.array([math.cos(p) * math.sin(y), math.sin(p), math.cos(p) * math.cos(y)])
    np.testing.assert_allclose(c2w[:3, 3], expected, atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 2], -expected / 3.0, atol=1e-12)  # looking at the origin
    np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)


def test_camera_orbits_world_origin_not_lookat() -> None:
    # EG3D quirk: the sphere is about the origin even when looking at another point.
    c2w, _ = unpack_label(look_at_camera(yaw_deg=50.0, pitch_deg=10.0, radius=2.7, lookat=(0.3, 0.2, 0.5)))
    assert np.linalg.norm(c2w[:3, 3]) == pytest.approx(2.7)
    fwd = np.array([0.3, 0.2, 0.5]) - c2w[:3, 3]
    np.testing.assert_allclose(c2w[:3, 2], fwd / np.linalg.norm(fwd), atol=1e-12)


def test_roll_rotates_about_viewing_axis() -> None:
    base = look_at_camera()
    rolled = look_at_camera(roll_deg=90.0)
    np.testing.assert_array_equal(rolled[:16], look_at_cam2world(roll_deg=90.0).reshape(16))
    c2w0, _ = unpack_label(base)
    c2w, _ = unpack_label(rolled)
    np.testing.assert_allclose(c2w[:3, 3], c2w0[:3, 3])
    np.testing.assert_allclose(c2w[:3, 2], c2w0[:3, 2], atol=1e-12)  # same viewing axis
    # Right axis turns toward the (old) down axis: right' = world -y, down' = world -x.
    np.testing.assert_allclose(c2w[:3, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], [-1, 0, 0], atol=1e-12)
    # Image content turns counter-clockwise: a point right of the pivot moves to the top of the image.
    x0, y0 = _project(base, [0.1, 0.0, 0.2])
    x1, y1 = _project(rolled, [0.1, 0.0, 0.2])
    assert x0 > 0.5 and y0 == pytest.approx(0.5)
    assert y1 < 0.5 and x1 == pytest.approx(0.5)
    # Small positive roll: the subject's right-hand point rises slightly in the image (y decreases).
    assert _project(look_at_camera(roll_deg=5.0), [0.1, 0.0, 0.2])[1] < 0.5


def test_frontal_projection_orientation() -> None:
    label = look_at_camera()
    x, y = _project(label, [0.1, 0.1, 0.2])  # world +x, +y (up) of the pivot
    assert x > 0.5 and y < 0.5  # appears right and above the centre (image y grows downward)


def test_pack_unpack_round_trip() -> None:
    rng = np.random.default_rng(0)
    c2w = np.eye(4)
    c2w[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    c2w[:3, 3] = rng.normal(size=3)
    K = intrinsics(3.1, cx=0.45, cy=0.55, skew=0.01)
    label = pack_label(c2w, K)
    assert label.shape == (25,)
    np.testing.assert_array_equal(label[[3, 7, 11]], c2w[:3, 3])  # translation at 3, 7, 11
    np.testing.assert_array_equal(label[16:], K.reshape(9))
    c2w2, K2 = unpack_label(label)
    np.testing.assert_array_equal(c2w2, c2w)
    np.testing.assert_array_equal(K2, K)
    batch = stack_labels([label, look_at_camera()])
    assert batch.shape == (2, 25)
    with pytest.raises(ValueError):
        stack_labels([])
    with pytest.raises(ValueError):
        pack_label(np.eye(3), K)


def test_validate_camera_shapes() -> None:
    one = look_at_camera()
    cams, batched = validate_camera(one)
    assert cams.shape == (1, 25) and not batched and cams.dtype == np.float64
    cams, batched = validate_camera(np.stack([one, one]).astype(np.float32))
    assert cams.shape == (2, 25) and batched and cams.dtype == np.float64
    for bad in (np.zeros(24), np.zeros((0, 25)), np.zeros((2, 3, 25)), np.zeros((2, 26)), 3.0):
        with pytest.raises(ValueError, match=r"camera must have shape"):
            validate_camera(bad)
    with pytest.raises(ValueError, match="camera"):
        validate_camera("not a camera")


@pytest.mark.parametrize(
    ("index", "value", "pattern"),
    [
        (5, np.nan, r"camera contains NaN/Inf at camera\[1\]\[5\] \(cam2world\[1\]\[1\]\)"),
        (16, np.inf, r"camera contains NaN/Inf .*focal"),
        (14, 0.5, r"cam2world bottom row"),
        (15, 2.0, r"cam2world bottom row"),
        (16, 0.0, r"focal"),
        (20, -4.0, r"focal"),
        (22, 0.1, r"intrinsics"),
        (24, 2.0, r"intrinsics"),
    ],
)
def test_validate_camera_errors_name_the_field(index: int, value: float, pattern: str) -> None:
    cams = np.stack([look_at_camera(), look_at_camera()])
    cams[1, index] = value
    with pytest.raises(ValueError, match=pattern):
        validate_camera(cams)


def test_validate_camera_rejects_singular_rotation() -> None:
    label = look_at_camera()
    label[[0, 1, 2]] = 0.0  # first row of the rotation zeroed
    with pytest.raises(ValueError, match=r"cam2world rotation is singular"):
        validate_camera(label)


def test_validate_camera_accepts_off_centre_and_skew() -> None:
    label = look_at_camera(cx=0.47, cy=0.52, focal=fov_to_focal(20.0))
    label[17] = 0.01
    validate_camera(label)
