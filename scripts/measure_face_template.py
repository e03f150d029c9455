"""Measure lp3d.photo.alignment.FACE_TEMPLATE: where dlib's five landmarks sit on a head in EG3D's world.

Renders training identities of the procedural teacher frontally (EG3D's FFHQ camera) with their depth,
finds the five landmarks on each render (lp3d.photo.faces), lifts each to 3D along its pixel's ray by
the render's depth, and prints the mean over identities as the Python constant to paste.

    python scripts/measure_face_template.py [--identities 48] [--resolution 384]
"""

from __future__ import annotations

import argparse

import numpy as np

import lp3d_render
from lp3d.images import rgb_to_uint8
from lp3d.photo.faces import LANDMARK_NAMES, find_faces
from lp3d.render.camera import look_at_camera, unpack_label
from lp3d.render.native import native_triplane
from lp3d.teachers.procedural import ProceduralTeacher


def landmarks_3d(tri: lp3d_render.Triplane, resolution: int) -> np.ndarray | None:
    """The five landmarks (5, 3) of a head rendered frontally, in world units; None without a face."""
    cam = look_at_camera()
    out = lp3d_render.render(tri, cam, resolution=resolution, outputs=["rgb", "depth"])
    faces = find_faces(rgb_to_uint8(out["rgb"]))
    if not faces:
        return None
    c2w, k = unpack_label(cam)
    pts = []
    for x, y in faces[0].landmarks:
        # Pixel (x, y) has its centre at ((x + 0.5) / R, (y + 0.5) / R) of the image (EG3D's rays).
        u, v = (x + 0.5) / resolution, (y + 0.5) / resolution
        d_cam = np.array([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], 1.0])
        d = c2w[:3, :3] @ (d_cam / np.linalg.norm(d_cam))
        depth = float(out["depth"][min(resolution - 1, round(y)), min(resolution - 1, round(x))])
        pts.append(c2w[:3, 3] + depth * d)
    return np.array(pts)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--identities", type=int, default=48)
    p.add_argument("--resolution", type=int, default=384)
    args = p.parse_args()
    teacher = ProceduralTeacher(version=2)
    found = []
    for seed in range(args.identities):
        tri = teacher.sample(seed)
        pts = landmarks_3d(native_triplane(tri), args.resolution)
        if pts is not None:
            found.append(pts)
    stack = np.stack(found)
    mean = stack.mean(axis=0)
    print(f"# {len(found)} of {args.identities} identities; per-landmark spread (world units):")
    for name, m, s in zip(LANDMARK_NAMES, mean, stack.std(axis=0), strict=True):
        print(f"#   {name:16s} mean {np.round(m, 4)}  std {np.round(s, 4)}")
    print("FACE_TEMPLATE = np.array(\n    [")
    for m in mean:
        print(f"        [{m[0]:.4f}, {m[1]:.4f}, {m[2]:.4f}],")
    print("    ]\n)")


if __name__ == "__main__":
    main()
