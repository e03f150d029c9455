"""EG3D cameras: the one Python definition of the camera convention.

A camera is EG3D's 25-float *label* (``float64`` here):

* ``label[0:16]``: the **cam2world** 4x4 matrix, row-major, so the camera centre is at indices 3, 7
  and 11. Camera axes follow **OpenCV**: +x right, +y down, +z forward (the viewing direction).
  The world is **y-up**; the face sits near the origin looking toward +z, so the frontal camera is
  at +z looking toward -z.
* ``label[16:25]``: the 3x3 intrinsics ``[[fx, skew, cx], [0, fy, cy], [0, 0, 1]]``, row-major,
  **normalised by image size** (resolution independent; FFHQ: ``fx = fy = 4.2647``, ``cx = cy = 0.5``).

A batch is ``(B, 25)``. See ``docs/eg3d-rendering.md`` §5 for how the renderers use it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

#: Focal length of the FFHQ dataset labels (2985.29 / 700, EG3D ``fix_intrinsics``), normalised.
FFHQ_FOCAL = 4.2647
#: Camera distance from the world origin used by EG3D's FFHQ scripts (``avg_camera_radius``).
FFHQ_RADIUS = 2.7
#: Point EG3D's FFHQ scripts look at (``avg_camera_pivot``).
FFHQ_PIVOT = (0.0, 0.0, 0.2)

#: Length of a camera label.
LABEL_SIZE = 25

# EG3D's FOV_to_intrinsics uses these truncated constants; keep them so focal lengths match its scripts.
_EG3D_PI = 3.14159
_EG3D_SQRT2 = 1.414


def fov_to_focal(fov_deg: float) -> float:
    """Normalised focal length from a field of view in degrees, exactly as EG3D's ``FOV_to_intrinsics``.

    ``f = 1 / (tan(fov_deg * 3.14159 / 360) * 1.414)``. Two EG3D quirks are kept on purpose: pi is
    truncated to 3.14159 and there is a stray factor 1.414 (~sqrt 2), so ``fov_deg`` is *not* the true
    field of view of the result (the true full FOV is ``2 * atan(0.5 / f)``; for 18.837 deg EG3D gives
    f = 4.2634, a true FOV of 13.38 deg). Use it to reproduce EG3D's ``--fov-deg`` cameras.
    """
    fov_deg = float(fov_deg)
    if not (math.isfinite(fov_deg) and 0.0 < fov_deg < 180.0):
        raise ValueError(f"fov_deg must be finite and in (0, 180), got {fov_deg!r}")
    return 1.0 / (math.tan(fov_deg * _EG3D_PI / 360.0) * _EG3D_SQRT2)


def focal_to_fov(f: float) -> float:
    """Inverse of :func:`fov_to_focal` (EG3D's quirky "FOV" in degrees, not the true FOV)."""
    f = float(f)
    if not (math.isfinite(f) and f > 0.0):
        raise ValueError(f"focal must be finite and > 0, got {f!r}")
    return math.atan(1.0 / (f * _EG3D_SQRT2)) * 360.0 / _EG3D_PI


def intrinsics(focal: float, cx: float = 0.5, cy: float = 0.5, skew: float = 0.0) -> np.ndarray:
    """Normalised intrinsics ``K`` (3, 3) float64: ``[[focal, skew, cx], [0, focal, cy], [0, 0, 1]]``."""
    return np.array([[focal, skew, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def lookat_pose(
    h: float, v: float, *, radius: float = FFHQ_RADIUS, lookat: Sequence[float] = (0.0, 0.0, 0.0)
) -> np.ndarray:
    """cam2world (4, 4) float64 with EG3D's ``LookAtPoseSampler.sample(h, v, lookat, radius)`` semantics.

    ``h`` and ``v`` are EG3D's raw horizontal/vertical angles in radians; ``h = v = pi/2`` is frontal
    (camera at ``(0, 0, radius)``). With ``theta = h`` and
    ``phi = arccos(1 - 2 * clamp(v, 1e-5, pi - 1e-5) / pi)`` (note: *not* linear in ``v``), the
    camera centre is ``radius * (sin(phi) cos(pi - theta), cos(phi), sin(phi) sin(pi - theta))``:
    larger ``h`` moves it toward +x, smaller ``v`` moves it up (+y). The centre lies on a sphere about
    the **world origin, not the lookat point** (EG3D quirk); the camera then turns to face ``lookat``.
    Axes as EG3D's ``create_cam2world_matrix``: ``right = -normalize(cross((0,1,0), forward))``,
    ``down = normalize(cross(forward, right))``; columns ``(right, down, forward)``.
    """
    lookat_arr = np.asarray(lookat, dtype=np.float64)
    if lookat_arr.shape != (3,) or not np.all(np.isfinite(lookat_arr)):
        raise ValueError(f"lookat must be 3 finite floats, got {lookat!r}")
    if not (math.isfinite(radius) and radius > 0.0):
        raise ValueError(f"radius must be finite and > 0, got {radius!r}")
    theta = float(h)
    v = min(max(float(v), 1e-5), math.pi - 1e-5)
    phi = math.acos(1.0 - 2.0 * v / math.pi)
    origin = radius * np.array(
        [math.sin(phi) * math.cos(math.pi - theta), math.cos(phi), math.sin(phi) * math.sin(math.pi - theta)]
    )
    delta = lookat_arr - origin
    if np.linalg.norm(delta) < 1e-9:
        raise ValueError("lookat coincides with the camera centre; the viewing direction is undefined")
    forward = _normalize(delta)
    side = np.cross(np.array([0.0, 1.0, 0.0]), forward)
    if np.linalg.norm(side) < 1e-9:
        raise ValueError("camera looks straight up or down; the look-at frame is undefined")
    right = -_normalize(side)
    down = _normalize(np.cross(forward, right))
    cam2world = np.eye(4)
    cam2world[:3, :3] = np.stack([right, down, forward], axis=-1)
    cam2world[:3, 3] = origin
    return cam2world


def eg3d_angles(yaw_deg: float, pitch_deg: float) -> tuple[float, float]:
    """EG3D ``(h, v)`` (radians) for a camera at azimuth ``yaw_deg`` and elevation ``pitch_deg``.

    ``h = pi/2 + yaw`` and ``v = pi/2 * (1 - sin(pitch))`` (EG3D's ``phi`` is the polar angle, with
    ``cos(phi) = 1 - 2v/pi``). Note that EG3D scripts often perturb ``v`` *linearly*
    (``v = pi/2 + offset``); such an offset is not an elevation angle: use :func:`lookat_pose` for it.
    """
    if not -90.0 < pitch_deg < 90.0:
        raise ValueError(f"pitch_deg must be in (-90, 90), got {pitch_deg!r}")
    return math.pi / 2 + math.radians(yaw_deg), math.pi / 2 * (1.0 - math.sin(math.radians(pitch_deg)))


def yaw_pitch_from_eg3d_angles(h: float, v: float) -> tuple[float, float]:
    """Inverse of :func:`eg3d_angles`: ``(yaw_deg, pitch_deg)`` of EG3D's ``(h, v)``."""
    v = min(max(float(v), 1e-5), math.pi - 1e-5)
    return math.degrees(h - math.pi / 2), math.degrees(math.asin(1.0 - 2.0 * v / math.pi))


def look_at_cam2world(
    *,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    radius: float = FFHQ_RADIUS,
    lookat: Sequence[float] = FFHQ_PIVOT,
) -> np.ndarray:
    """cam2world (4, 4) float64 of :func:`look_at_camera` (same angles and sign conventions)."""
    h, v = eg3d_angles(yaw_deg, pitch_deg)
    cam2world = lookat_pose(h, v, radius=radius, lookat=lookat)
    r = math.radians(roll_deg)
    c, s = math.cos(r), math.sin(r)
    # Right-handed rotation about the camera's +z (viewing) axis, applied in camera coordinates.
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cam2world[:3, :3] = cam2world[:3, :3] @ roll
    return cam2world


def look_at_camera(
    *,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    radius: float = FFHQ_RADIUS,
    lookat: Sequence[float] = FFHQ_PIVOT,
    focal: float = FFHQ_FOCAL,
    cx: float = 0.5,
    cy: float = 0.5,
) -> np.ndarray:
    """A look-at camera label (25,) float64 from geometric angles in degrees.

    Sign conventions (all angles are of the camera *centre*, seen from the world origin):

    * ``yaw_deg``: azimuth about the world +y axis, from +z toward +x. ``yaw_deg > 0`` moves the camera
      toward +x (the subject's left side, since the subject faces +z). EG3D: ``h = pi/2 + yaw``.
    * ``pitch_deg``: true elevation above the xz plane, in (-90, 90). ``pitch_deg > 0`` puts the camera
      above, looking down. EG3D: ``v = pi/2 * (1 - sin(pitch))`` (see :func:`eg3d_angles`).
    * ``roll_deg``: rotation about the viewing axis (camera +z), right-handed in OpenCV camera axes:
      ``cam2world[:3, :3] @ Rz(roll)``. ``roll_deg > 0`` turns the camera's right axis toward its down
      axis, i.e. the camera turns clockwise as seen from behind it and the image content turns
      counter-clockwise.

    The centre is at ``radius * (cos(pitch) sin(yaw), sin(pitch), cos(pitch) cos(yaw))``, on a sphere
    about the world origin (EG3D quirk), and the camera faces ``lookat`` (default: the FFHQ pivot
    (0, 0, 0.2), as EG3D's gen_videos.py). All-zero angles give EG3D's frontal FFHQ camera.
    """
    cam2world = look_at_cam2world(
        yaw_deg=yaw_deg, pitch_deg=pitch_deg, roll_deg=roll_deg, radius=radius, lookat=lookat
    )
    return pack_label(cam2world, intrinsics(focal, cx=cx, cy=cy))


def pack_label(cam2world: ArrayLike, K: ArrayLike) -> np.ndarray:
    """25-float label (25,) float64 from cam2world (4, 4) and normalised intrinsics K (3, 3)."""
    c2w = np.asarray(cam2world, dtype=np.float64)
    k = np.asarray(K, dtype=np.float64)
    if c2w.shape != (4, 4):
        raise ValueError(f"cam2world must have shape (4, 4), got {c2w.shape}")
    if k.shape != (3, 3):
        raise ValueError(f"intrinsics must have shape (3, 3), got {k.shape}")
    return np.concatenate([c2w.reshape(16), k.reshape(9)])


def unpack_label(label: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``(cam2world (4, 4), K (3, 3))`` float64 copies from a label (25,)."""
    lab = np.asarray(label, dtype=np.float64)
    if lab.shape != (LABEL_SIZE,):
        raise ValueError(f"camera label must have shape (25,), got {lab.shape}")
    return lab[:16].reshape(4, 4).copy(), lab[16:].reshape(3, 3).copy()


def stack_labels(labels: Sequence[ArrayLike]) -> np.ndarray:
    """Batch (B, 25) float64 from a non-empty sequence of (25,) labels."""
    if len(labels) == 0:
        raise ValueError("stack_labels needs at least one camera label")
    arrs = [np.asarray(lab, dtype=np.float64) for lab in labels]
    for i, a in enumerate(arrs):
        if a.shape != (LABEL_SIZE,):
            raise ValueError(f"camera label {i} must have shape (25,), got {a.shape}")
    return np.stack(arrs)


def _field_name(index: int) -> str:
    """Human name of label entry ``index`` (used in error messages)."""
    if index < 16:
        return f"cam2world[{index // 4}][{index % 4}]"
    names = {
        16: "intrinsics fx (focal)",
        17: "intrinsics skew",
        18: "intrinsics cx",
        20: "intrinsics fy (focal)",
        21: "intrinsics cy",
    }
    return names.get(index, f"intrinsics[{(index - 16) // 3}][{(index - 16) % 3}]")


def validate_camera(camera: ArrayLike) -> tuple[np.ndarray, bool]:
    """Check a camera label and return ``(cameras (B, 25) float64 copy, was_batched)``.

    Accepts (25,) (``was_batched = False``, returned as B = 1) or (B, 25) with B >= 1. Raises
    ValueError naming the problem ('camera', 'cam2world', 'focal' or 'intrinsics'): wrong shape,
    NaN/Inf, a cam2world bottom row other than (0, 0, 0, 1), a singular rotation (|det| < 1e-6),
    a focal length fx or fy <= 0, or an intrinsics last row other than (0, 0, 1). Tolerance 1e-6.
    """
    try:
        cams = np.array(camera, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"camera must be a float array of shape (25,) or (B, 25): {e}") from None
    if cams.ndim == 1 and cams.shape == (LABEL_SIZE,):
        was_batched = False
        cams = cams[None, :]
    elif cams.ndim == 2 and cams.shape[1] == LABEL_SIZE and cams.shape[0] >= 1:
        was_batched = True
    else:
        raise ValueError(f"camera must have shape (25,) or (B, 25) with B >= 1, got {cams.shape}")
    bad = ~np.isfinite(cams)
    if bad.any():
        b, i = (int(x) for x in np.argwhere(bad)[0])
        raise ValueError(f"camera contains NaN/Inf at camera[{b}][{i}] ({_field_name(i)})")
    for b, cam in enumerate(cams):
        c2w = cam[:16].reshape(4, 4)
        if np.max(np.abs(c2w[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > 1e-6:
            raise ValueError(f"camera {b}: cam2world bottom row must be (0, 0, 0, 1), got {c2w[3].tolist()}")
        det = float(np.linalg.det(c2w[:3, :3]))
        if abs(det) < 1e-6:
            raise ValueError(f"camera {b}: cam2world rotation is singular/degenerate (det = {det:.3g})")
        k = cam[16:].reshape(3, 3)
        if k[0, 0] <= 0.0 or k[1, 1] <= 0.0:
            raise ValueError(
                f"camera {b}: intrinsics focal fx and fy must be > 0, "
                f"got fx = {float(k[0, 0])}, fy = {float(k[1, 1])}"
            )
        if np.max(np.abs(k[2] - np.array([0.0, 0.0, 1.0]))) > 1e-6 or abs(k[1, 0]) > 1e-6:
            raise ValueError(
                f"camera {b}: intrinsics must be [[fx, skew, cx], [0, fy, cy], [0, 0, 1]], "
                f"got last row {k[2].tolist()} and K[1][0] = {float(k[1, 0])}"
            )
    return np.ascontiguousarray(cams), was_batched


def camera_summary(label: np.ndarray) -> dict[str, float]:
    """A camera label as yaw/pitch of its centre about the origin (as ``look_at_camera`` takes them),
    radius and focal length."""
    c2w = np.asarray(label, np.float64)[:16].reshape(4, 4)
    centre = c2w[:3, 3]
    radius = float(np.linalg.norm(centre))
    yaw = math.degrees(math.atan2(centre[0], centre[2]))
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, centre[1] / radius)))) if radius > 0 else 0.0
    return {"yaw_deg": yaw, "pitch_deg": pitch, "radius": radius, "focal": float(label[16])}


def orbit_angles(frames: int, yaw_range: float, pitch_range: float) -> list[tuple[float, float]]:
    """(yaw, pitch offset) per frame of a closed loop, as EG3D's videos: ``yaw = R_y sin(2 pi t)``,
    ``pitch = R_p cos(2 pi t)`` with ``t = i / frames`` (the last frame leads back to the first)."""
    out = []
    for i in range(frames):
        t = 2.0 * math.pi * i / frames
        out.append((yaw_range * math.sin(t), pitch_range * math.cos(t)))
    return out
