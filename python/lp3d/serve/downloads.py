"""What a lifted photo's download links make, in memory (nothing touches the disk): the triplane file,
its share page, a mesh and an orbit GIF."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["DOWNLOADS", "ORBIT", "Orbit", "download_bytes"]


@dataclass(frozen=True)
class Orbit:
    """The orbit GIF: raw volume renders (no super-resolution, as the page draws) swinging through
    ``±yaw_range`` degrees, as ``lp3d orbit --raw`` makes them but smaller and with fewer samples per
    ray, so a download takes seconds on a CPU renderer (``lp3d orbit`` makes the full-quality one)."""

    frames: int = 16
    yaw_range: float = 35.0
    resolution: int = 96
    samples: tuple[int, int] = (24, 24)
    fps: float = 12.0


ORBIT = Orbit()

#: Download kinds: suffix -> (media type, what it is, for messages).
DOWNLOADS = {
    "npz": ("application/octet-stream", "the triplane"),
    "html": ("text/html; charset=utf-8", "its share page"),
    "glb": ("model/gltf-binary", "a mesh (marching cubes at EG3D's threshold, glTF binary)"),
    "gif": ("image/gif", "an orbit GIF"),
}


def _orbit_gif(tri: Any, orbit: Orbit) -> bytes:
    from lp3d.images import rgb_to_uint8
    from lp3d.outputs import gif_bytes
    from lp3d.render.camera import look_at_camera, orbit_angles
    from lp3d.render.native import render

    angles = orbit_angles(orbit.frames, orbit.yaw_range, 0.0)
    cams = np.stack([look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in angles])
    coarse, fine = orbit.samples
    rgb = render(
        tri,
        cams,
        resolution=orbit.resolution,
        depth_resolution=coarse,
        depth_resolution_importance=fine,
        outputs=["rgb"],
    )["rgb"]
    return gif_bytes([rgb_to_uint8(frame) for frame in rgb], orbit.fps)


def download_bytes(tri: Any, kind: str, title: str, *, orbit: Orbit = ORBIT) -> bytes:
    """The ``kind`` download (a key of :data:`DOWNLOADS`) of the TriplaneData ``tri``. Raises
    :class:`~lp3d.render.mesh.MeshError` (a ValueError) for a field with no surface to mesh."""
    if kind == "npz":
        from lp3d.render.triplane_io import triplane_bytes

        return triplane_bytes(tri)
    if kind == "html":
        from lp3d.share import build_page

        return build_page(tri, title=title).encode("utf-8")
    if kind == "glb":
        from lp3d.render.mesh import extract_mesh, glb_bytes

        return glb_bytes(extract_mesh(tri))
    if kind == "gif":
        return _orbit_gif(tri, orbit)
    raise ValueError(f"unknown download {kind!r}: expected one of {sorted(DOWNLOADS)}")
