"""The camera of a photo and its training-framed crop, from the face's five landmarks.

The encoder was trained on renders taken by EG3D's FFHQ look-at camera (radius 2.7, focal 4.2647,
looking at (0, 0, 0.2)) at some yaw and pitch. A photo is framed that way when its five landmarks
(:mod:`lp3d.photo.faces`) fall where :data:`FACE_TEMPLATE`, the landmarks' mean position on a head in
EG3D's world frame, projects under such a camera. :func:`align_face` finds both at once:

* for every (yaw, pitch) on a grid (then a finer one around the best), the similarity (scale, roll,
  shift) that carries the photo's landmarks closest, in least squares, onto the template's projection
  at that camera: a closed form (Procrustes in the complex plane);
* the pose whose best similarity leaves the least error (with a weak prior toward the frontal pose
  that portraits are mostly taken from) wins; its similarity is the crop
  (:class:`~lp3d.photo.framing.Crop`: centre, side and roll) and its look-at camera the photo's.

Yaw is seen in how far the nose base sits from the eyes' midline and in the two eyes' foreshortening;
pitch in the nose base's height under the eye line. A person whose nose is longer than the template's
reads as pitched, so pitch is the less certain of the two (docs/photos-and-video.md measures both).

May import :mod:`lp3d.render` (the camera convention).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from lp3d.photo.framing import Crop
from lp3d.render.camera import FFHQ_FOCAL, look_at_cam2world

__all__ = [
    "FACE_TEMPLATE",
    "MAX_PITCH_DEG",
    "MAX_YAW_DEG",
    "FaceAlignment",
    "align_face",
    "project_template",
]

#: The five landmarks (:data:`lp3d.photo.faces.LANDMARK_NAMES`, the person's right eye first) of a head
#: in EG3D's world frame (y up, the face toward +z), world units. Measured by
#: ``python scripts/measure_face_template.py``: dlib's landmarks on frontal renders of the procedural
#: teacher's training identities, lifted to 3D by each render's depth, averaged.
FACE_TEMPLATE = np.array(
    [
        [0.0709, 0.0493, 0.1636],
        [0.0285, 0.0469, 0.1766],
        [-0.0702, 0.0503, 0.1636],
        [-0.0277, 0.0475, 0.1772],
        [-0.0002, -0.0340, 0.1801],
    ]
)
#: The pose search's range (degrees): a little beyond the training data's reference views (±49° yaw,
#: ±26° pitch), so that a photo just outside is found at the edge of what the encoder knows.
MAX_YAW_DEG = 60.0
MAX_PITCH_DEG = 40.0
#: The misfit's scale and the pose prior of :func:`align_face`: the landmarks' position noise (a
#: fraction of the crop side) and the spread of yaw and pitch among portraits (degrees). Five landmarks
#: on a nearly flat patch of the face tell pitch poorly (a long nose reads as a camera from above), so
#: without the prior a frontal photo could be framed as seen from 25° above.
LANDMARK_NOISE = 0.01
PRIOR_YAW_DEG = 30.0
PRIOR_PITCH_DEG = 10.0
_COARSE_STEP = 1.0
_FINE_STEP = 0.1
_COARSE_YAWS = np.arange(-MAX_YAW_DEG, MAX_YAW_DEG + 1e-9, _COARSE_STEP)
_COARSE_PITCHES = np.arange(-MAX_PITCH_DEG, MAX_PITCH_DEG + 1e-9, _COARSE_STEP)


@dataclass(frozen=True)
class FaceAlignment:
    """A photo's face put in the training framing: the look-at camera's ``yaw_deg`` and ``pitch_deg``
    (as :func:`lp3d.render.camera.look_at_camera` takes them), ``roll_deg`` (the face's tilt in the
    image, levelled by the crop), the ``crop`` and the landmarks' root-mean-square misfit after
    alignment, ``residual`` (a fraction of the crop side)."""

    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    crop: Crop
    residual: float


def project_template(yaws_deg: np.ndarray, pitches_deg: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Where ``template`` (5, 3) projects in the image of FFHQ's look-at camera at each (yaw, pitch)
    (N,), in units of the image size ((0, 0) the top-left corner, (1, 1) the bottom-right): (N, 5, 2)."""
    out = np.empty((len(yaws_deg), len(template), 2))
    for i, (y, p) in enumerate(zip(yaws_deg, pitches_deg, strict=True)):
        c2w = look_at_cam2world(yaw_deg=float(y), pitch_deg=float(p))
        cam = (template - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera axes (x right, y down, z forward)
        out[i] = FFHQ_FOCAL * cam[:, :2] / cam[:, 2:3] + 0.5
    return out


def _procrustes(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares similarities carrying ``src`` (5, 2) onto each of ``dst`` (N, 5, 2), as complex
    numbers: ``(a (N,), residual (N,))`` with ``dst ≈ a (src - mean src) + mean dst``."""
    z = src[:, 0] + 1j * src[:, 1]
    z = z - z.mean()
    w = dst[..., 0] + 1j * dst[..., 1]
    w = w - w.mean(axis=1, keepdims=True)
    a = (np.conj(z)[None] * w).sum(axis=1) / max(float(np.vdot(z, z).real), 1e-12)
    resid = np.abs(w - a[:, None] * z[None]) ** 2
    return a, resid.sum(axis=1)


@functools.lru_cache(maxsize=4)
def _coarse_projections(template_bytes: bytes) -> np.ndarray:
    """The template's projections on the coarse grid (every face of a video shares them)."""
    template = np.frombuffer(template_bytes).reshape(-1, 3)
    yy, pp = _grid(_COARSE_YAWS, _COARSE_PITCHES)
    return project_template(yy, pp, template)


def _fine_grid(y0: float, p0: float) -> tuple[np.ndarray, np.ndarray]:
    """The fine search's yaws and pitches around the coarse grid's best pose ``(y0, p0)``."""
    fine = np.arange(-1.0, 1.0 + 1e-9, _FINE_STEP)
    return np.clip(y0 + fine, -MAX_YAW_DEG, MAX_YAW_DEG), np.clip(p0 + fine, -MAX_PITCH_DEG, MAX_PITCH_DEG)


@functools.lru_cache(maxsize=256)
def _fine_projections(y0: float, p0: float, template_bytes: bytes) -> np.ndarray:
    """The template's projections on the fine grid about a coarse pose: the faces of a video or a
    live stream come back to the same few coarse poses, so each is projected once."""
    template = np.frombuffer(template_bytes).reshape(-1, 3)
    return project_template(*_grid(*_fine_grid(y0, p0)), template)


def _grid(yaws: np.ndarray, pitches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    yy, pp = np.meshgrid(yaws, pitches, indexing="ij")
    return yy.ravel(), pp.ravel()


def _best_pose(
    landmarks: np.ndarray,
    yaws: np.ndarray,
    pitches: np.ndarray,
    template: np.ndarray,
    prior: bool,
    projections: np.ndarray | None = None,
) -> tuple[int, np.ndarray, np.ndarray]:
    yy, pp = _grid(yaws, pitches)
    if projections is None:
        projections = project_template(yy, pp, template)
    a, resid = _procrustes(landmarks, projections)
    cost = resid / LANDMARK_NOISE**2
    if prior:
        cost = cost + (yy / PRIOR_YAW_DEG) ** 2 + (pp / PRIOR_PITCH_DEG) ** 2
    i = int(np.argmin(cost))
    return i, np.array([yy[i], pp[i], resid[i]]), a


def align_face(
    landmarks: np.ndarray, template: np.ndarray | None = None, *, prior: bool = True
) -> FaceAlignment:
    """The camera and training-framed crop of a face whose five landmarks are ``landmarks`` (5, 2)
    (source pixels, dlib's order); ``template`` defaults to :data:`FACE_TEMPLATE` (module docstring).
    ``prior=False`` drops the pull toward the frontal pose (the least-squares pose alone)."""
    pts = np.asarray(landmarks, np.float64)
    if pts.shape != (5, 2) or not np.isfinite(pts).all():
        raise ValueError(f"landmarks must be (5, 2) finite pixel positions, got shape {pts.shape}")
    tpl = FACE_TEMPLATE if template is None else np.asarray(template, np.float64)
    tpl_bytes = np.ascontiguousarray(tpl, np.float64).tobytes()
    coarse = _coarse_projections(tpl_bytes)
    _, (y0, p0, _), _ = _best_pose(pts, _COARSE_YAWS, _COARSE_PITCHES, tpl, prior, coarse)
    yaws, pitches = _fine_grid(float(y0), float(p0))
    fine = _fine_projections(float(y0), float(p0), tpl_bytes)
    i, (yaw, pitch, resid), a = _best_pose(pts, yaws, pitches, tpl, prior, fine)
    a_best = complex(a[i])
    qm = project_template(np.array([yaw]), np.array([pitch]), tpl)[0].mean(axis=0)
    lm = pts.mean(axis=0)
    # The crop maps source pixel L to crop position a (L - mean L) + mean q (units of the crop side):
    # its centre (position 0.5, 0.5) is at L = mean L + (0.5 - mean q) / a, its side 1 / |a| pixels.
    # Pixel centres sit at integers on both sides, so the centre needs no half-pixel shift.
    c = complex(lm[0], lm[1]) + (complex(0.5, 0.5) - complex(qm[0], qm[1])) / a_best
    roll = -math.degrees(math.atan2(a_best.imag, a_best.real))
    crop = Crop(cx=c.real, cy=c.imag, side=1.0 / abs(a_best), angle_deg=roll)
    return FaceAlignment(
        yaw_deg=float(yaw),
        pitch_deg=float(pitch),
        roll_deg=roll,
        crop=crop,
        residual=math.sqrt(float(resid) / len(pts)),
    )
