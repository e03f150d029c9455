"""Random and band-limited triplanes with EG3D-scaled decoders, and the parity tests' cameras:
the scenes every renderer test draws from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lp3d.render.camera import look_at_camera
from lp3d.render.triplane import TriplaneData


@dataclass(frozen=True)
class Scene:
    """The same triplane for the float64 reference (``data``) and the GPU renderer (``native``)."""

    data: TriplaneData
    native: object


def make_scene(
    *,
    size: tuple[int, int] = (64, 64),
    decoder: str = "realistic",
    seed: int = 0,
    dtype: type = np.float32,
    ray_start: float = 2.25,
    ray_end: float = 3.3,
    box_warp: float = 1.0,
) -> Scene:
    """A random triplane with an EG3D-scaled decoder.

    ``decoder="realistic"``: random planes (white noise drawn at <= 64 x 64 texels, bilinearly
    upsampled to ``size``, so every size has the same roughness per unit length) and EG3D's
    initialisation scales (w0 ~ N(0,1)/sqrt(32),
    w1 ~ N(0,1)/8), so densities vary gently. ``decoder="strong"``: band-limited planes (a few
    sinusoids per channel) and a density row scaled up so raw densities swing over tens of units
    within a ray: opaque walls, empty gaps and sharply concentrated importance samples.

    Why limit roughness: the parity tolerances hold a float32 renderer to the float64 answer, which
    is only meaningful when the scene's answer is itself determined to that precision in float32.
    White noise under a 12x density gain is a random fog whose float64 render moves by ~2e-3 when
    the camera moves by 2e-7 (one float32 rounding), and 256 x 256 white noise moves it by ~3e-5.
    Likewise the strong planes taper to zero at their borders: EG3D's zeros padding fades a plane to
    0 within half a texel of its edge, and under a 12x density gain that fade is a wall with slope
    ~3e3 per unit at 256 x 256. ``test_parity_scenes_are_well_conditioned`` checks every parity
    scene; rough fog and hard edges are covered by the stress tests with a conditioning-aware
    tolerance.
    """
    rng = np.random.default_rng(seed)
    h, w = size
    if decoder == "strong":
        planes = smooth_planes(rng, h, w).astype(dtype)
    else:
        noise = rng.standard_normal((3, 32, min(h, 64), min(w, 64)))
        planes = upsample_bilinear(noise, h, w).astype(dtype)
    w0 = (rng.standard_normal((64, 32)) / np.sqrt(32)).astype(np.float32)
    b0 = (0.1 * rng.standard_normal(64)).astype(np.float32)
    w1 = (rng.standard_normal((33, 64)) / 8).astype(np.float32)
    b1 = (0.1 * rng.standard_normal(33)).astype(np.float32)
    if decoder == "strong":
        w0 *= 3.0
        w1[0] *= 12.0
        b1[0] = -4.0
    elif decoder != "realistic":
        raise ValueError(decoder)
    data = TriplaneData(
        planes=planes, w0=w0, b0=b0, w1=w1, b1=b1, box_warp=box_warp, ray_start=ray_start, ray_end=ray_end
    )
    return Scene(data=data, native=data.to_native())


def upsample_bilinear(x: np.ndarray, h: int, w: int) -> np.ndarray:
    """Resize the last two axes of ``x`` to (h, w) by separable linear interpolation (corners aligned)."""
    ys = np.linspace(0, x.shape[-2] - 1, h)
    xs = np.linspace(0, x.shape[-1] - 1, w)
    rows = np.apply_along_axis(lambda r: np.interp(xs, np.arange(x.shape[-1]), r), -1, x)
    return np.apply_along_axis(lambda c: np.interp(ys, np.arange(x.shape[-2]), c), -2, rows)


def smooth_planes(rng: np.random.Generator, h: int, w: int, n_waves: int = 4) -> np.ndarray:
    """(3, 32, h, w) fields, each a sum of ``n_waves`` random sinusoids of at most 3 cycles per plane."""
    v = np.linspace(-1.0, 1.0, h)[:, None]
    u = np.linspace(-1.0, 1.0, w)[None, :]
    out = np.zeros((3, 32, h, w))
    for _ in range(n_waves):
        fu, fv = rng.uniform(-1.5, 1.5, size=(2, 3, 32, 1, 1))
        phase = rng.uniform(0, 2 * np.pi, size=(3, 32, 1, 1))
        amp = rng.uniform(0.3, 1.0, size=(3, 32, 1, 1))
        out += amp * np.sin(np.pi * (fu * u + fv * v) + phase)
    # Cosine taper over the outer 15% so the plane meets its zero padding smoothly.
    taper = lambda a: np.clip((1.0 - np.abs(a)) / 0.15, 0.0, 1.0)  # noqa: E731
    window = 0.5 - 0.5 * np.cos(np.pi * taper(v) * taper(u))
    return out * window


#: The camera set of the parity tests: frontal, +-45 deg yaw, +-25 deg pitch, rolled, off-centre
#: principal point (all 25-float EG3D labels).
PARITY_CAMERAS: dict[str, np.ndarray] = {
    "frontal": look_at_camera(),
    "yaw+45": look_at_camera(yaw_deg=45.0),
    "yaw-45": look_at_camera(yaw_deg=-45.0),
    "pitch+25": look_at_camera(pitch_deg=25.0),
    "pitch-25": look_at_camera(pitch_deg=-25.0),
    "rolled": look_at_camera(yaw_deg=10.0, roll_deg=20.0),
    "off-centre": look_at_camera(yaw_deg=-15.0, pitch_deg=10.0, cx=0.62, cy=0.41),
}
