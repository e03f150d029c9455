"""The paper's camera distributions for synthetic training data, as batches of 25-float EG3D labels.

Paper §3.2 ("On-the-fly augmentation") and supplement "Camera augmentation":

* **Reference (input) cameras** ``P_ref``: EG3D's fixed camera is augmented with random focal length,
  radius, principal point and roll. FFHQ: FOV ~ N(18.83°, 1°) (EG3D's ``FOV_to_intrinsics`` degrees,
  see :func:`lp3d.render.camera.fov_to_focal`), radius ~ N(2.7, 0.1), principal point ~ N(256, 14) px of a
  512 px image, roll ~ N(0°, 2°); pose within ±26° pitch and ±49° yaw of the front of the face.
* **Multiview cameras** ``P_mv``: "fixed values as in the EG3D model" (FFHQ intrinsics ``f = 4.2647``,
  ``c = 0.5``, radius 2.7, no roll); pose within ±26° pitch and ±36° yaw.

Choice where the paper is vague: pitch and yaw are drawn **uniformly** within their ranges. The paper
speaks of a pitch/yaw "range" and the supplement figure shows the "limits" of the pose distribution,
i.e. a bounded support (a normal would have none); with no real-data pose prior to follow (the data
is synthetic), uniform is the plain reading. The angles are true azimuth/elevation of the camera
centre about the world origin (:func:`lp3d.render.camera.look_at_camera`), looking at the FFHQ pivot.

Every number is drawn vectorised from one generator (``numpy.random.Generator`` or
``torch.Generator``), so a batch is reproducible from the generator state; the labels themselves are
built by :func:`lp3d.render.camera.look_at_camera`, the one definition of the camera convention.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch

from lp3d.render.camera import FFHQ_FOCAL, FFHQ_PIVOT, FFHQ_RADIUS, fov_to_focal, look_at_camera

__all__ = [
    "AFHQ_REFERENCE",
    "EG3D_FOV_DEG",
    "FFHQ_MULTIVIEW",
    "FFHQ_REFERENCE",
    "CameraDistribution",
    "CameraSample",
    "Generator",
    "sample_cameras",
]

#: EG3D's FFHQ field of view in its ``FOV_to_intrinsics`` degrees (the paper's "focal length of 18.83").
EG3D_FOV_DEG = 18.83

Generator = np.random.Generator | torch.Generator


@dataclass(frozen=True)
class CameraDistribution:
    """A distribution over cameras; every spread of 0 means "fixed".

    Pose: yaw uniform in ``[-yaw_range_deg, yaw_range_deg]``, pitch uniform in
    ``[-pitch_range_deg, pitch_range_deg]`` (true azimuth / elevation, degrees). Intrinsics: when
    ``fov_std_deg > 0`` or ``focal`` is None the focal length is ``fov_to_focal(N(fov_mean_deg,
    fov_std_deg))``, else ``focal``. Principal point ``N(principal_mean_px, principal_std_px)`` in
    pixels of a ``principal_image_px`` image, stored normalised (``cx = px / principal_image_px``).
    Radius ``N(radius_mean, radius_std)``, roll ``N(0, roll_std_deg)``.
    """

    name: str = "custom"
    yaw_range_deg: float = 49.0
    pitch_range_deg: float = 26.0
    fov_mean_deg: float = EG3D_FOV_DEG
    fov_std_deg: float = 1.0
    #: Fixed normalised focal length used when ``fov_std_deg == 0`` (None: ``fov_to_focal(fov_mean_deg)``).
    focal: float | None = None
    radius_mean: float = FFHQ_RADIUS
    radius_std: float = 0.1
    principal_mean_px: float = 256.0
    principal_std_px: float = 14.0
    principal_image_px: float = 512.0
    roll_std_deg: float = 2.0
    lookat: tuple[float, float, float] = FFHQ_PIVOT

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("name", "lookat", "focal"):
                continue
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"CameraDistribution.{f.name} must be finite and >= 0, got {value!r}")
        if not 0 < self.fov_mean_deg < 180:
            raise ValueError(f"CameraDistribution.fov_mean_deg must be in (0, 180), got {self.fov_mean_deg}")
        if self.pitch_range_deg >= 89.0:
            raise ValueError(
                "CameraDistribution.pitch_range_deg must be < 89 (the look-at frame degenerates)"
            )
        if self.radius_mean <= 0 or self.principal_image_px <= 0:
            raise ValueError("CameraDistribution.radius_mean and principal_image_px must be > 0")
        if self.focal is not None and not (np.isfinite(self.focal) and self.focal > 0):
            raise ValueError(f"CameraDistribution.focal must be finite and > 0, got {self.focal!r}")
        if len(self.lookat) != 3:
            raise ValueError(f"CameraDistribution.lookat must have 3 entries, got {self.lookat!r}")

    @property
    def mean_focal(self) -> float:
        """The normalised focal length at the mean FOV (or the fixed ``focal``)."""
        if self.focal is not None and self.fov_std_deg == 0:
            return float(self.focal)
        return fov_to_focal(self.fov_mean_deg)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["lookat"] = list(self.lookat)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CameraDistribution:
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"CameraDistribution.from_dict: unknown keys {unknown}")
        kwargs = dict(data)
        if "lookat" in kwargs:
            kwargs["lookat"] = tuple(kwargs["lookat"])
        return cls(**kwargs)


#: Supplement "Camera augmentation", FFHQ, and §3.2's reference pose range (±26° pitch, ±49° yaw).
FFHQ_REFERENCE = CameraDistribution(name="ffhq-reference")
#: §3.2: multiview cameras use EG3D's fixed FFHQ values; pose range ±26° pitch, ±36° yaw.
FFHQ_MULTIVIEW = CameraDistribution(
    name="ffhq-multiview",
    yaw_range_deg=36.0,
    pitch_range_deg=26.0,
    fov_std_deg=0.0,
    focal=FFHQ_FOCAL,
    radius_std=0.0,
    principal_std_px=0.0,
    roll_std_deg=0.0,
)
#: Supplement "Camera augmentation", AFHQ (wider focal, principal point and roll spreads).
AFHQ_REFERENCE = CameraDistribution(
    name="afhq-reference", fov_std_deg=1.5, principal_std_px=25.0, roll_std_deg=6.0
)


@dataclass(frozen=True)
class CameraSample:
    """A batch of B sampled cameras and the parameters they were built from (all float64 arrays (B,)).

    ``labels`` (B, 25): EG3D labels (None when not asked for). ``focal``, ``cx``, ``cy`` are normalised
    intrinsics; angles are degrees; ``fov_deg`` is EG3D's FOV degrees (NaN where the focal length was fixed).
    """

    labels: np.ndarray | None
    yaw_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    radius: np.ndarray
    fov_deg: np.ndarray
    focal: np.ndarray
    cx: np.ndarray
    cy: np.ndarray


def _normal(gen: Generator, n: int) -> np.ndarray:
    if isinstance(gen, torch.Generator):
        return torch.randn(n, generator=gen, dtype=torch.float64).numpy()
    return gen.standard_normal(n)


def _uniform(gen: Generator, n: int) -> np.ndarray:
    """U[-1, 1)."""
    if isinstance(gen, torch.Generator):
        u = torch.rand(n, generator=gen, dtype=torch.float64).numpy()
    else:
        u = gen.random(n)
    return 2.0 * u - 1.0


def sample_cameras(
    dist: CameraDistribution, n: int, generator: Generator, *, labels: bool = True
) -> CameraSample:
    """Draw ``n`` cameras from ``dist``.

    The draws are made in a fixed order (yaw, pitch, fov, radius, cx, cy, roll; a quantity with zero
    spread draws nothing), each as one vectorised call, so the same generator state gives the same
    batch. The labels are then built per camera by :func:`lp3d.render.camera.look_at_camera` (one call
    each); ``labels=False`` skips that (same draws), e.g. to study the distribution on millions of samples.

    Returns:
        A :class:`CameraSample`; ``labels`` is (n, 25) float64, or None when ``labels=False``.
    """
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    if not isinstance(generator, np.random.Generator | torch.Generator):
        raise TypeError(
            f"generator must be a numpy.random.Generator or torch.Generator, got {type(generator).__name__}"
        )

    def normal(mean: float, std: float) -> np.ndarray:
        return mean + std * _normal(generator, n) if std > 0 else np.full(n, float(mean))

    def uniform(half_range: float) -> np.ndarray:
        return half_range * _uniform(generator, n) if half_range > 0 else np.zeros(n)

    yaw = uniform(dist.yaw_range_deg)
    pitch = uniform(dist.pitch_range_deg)
    if dist.fov_std_deg > 0 or dist.focal is None:
        fov = normal(dist.fov_mean_deg, dist.fov_std_deg)
        # 5 sigma below 18.83° is still ~14°; clip only against nonsense far in the tails.
        fov = np.clip(fov, 1.0, 170.0)
        focal = np.array([fov_to_focal(f) for f in fov])
    else:
        fov = np.full(n, np.nan)
        focal = np.full(n, float(dist.focal))
    radius = np.maximum(normal(dist.radius_mean, dist.radius_std), 1e-3)
    cx = normal(dist.principal_mean_px, dist.principal_std_px) / dist.principal_image_px
    cy = normal(dist.principal_mean_px, dist.principal_std_px) / dist.principal_image_px
    roll = normal(0.0, dist.roll_std_deg)

    built = None
    if labels:
        built = np.stack(
            [
                look_at_camera(
                    yaw_deg=float(yaw[i]),
                    pitch_deg=float(pitch[i]),
                    roll_deg=float(roll[i]),
                    radius=float(radius[i]),
                    lookat=dist.lookat,
                    focal=float(focal[i]),
                    cx=float(cx[i]),
                    cy=float(cy[i]),
                )
                for i in range(n)
            ]
        )
    return CameraSample(
        labels=built,
        yaw_deg=yaw,
        pitch_deg=pitch,
        roll_deg=roll,
        radius=radius,
        fov_deg=fov,
        focal=focal,
        cx=cx,
        cy=cy,
    )
