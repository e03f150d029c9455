"""The camera and framing found from a face's landmarks (lp3d.photo.alignment), on held-out teacher
heads rendered at known cameras over the training data's reference-view ranges (yaw ±49°, pitch ±26°).

For each case: a held-out identity of the procedural teacher is rendered at a random look-at camera
(FFHQ's radius and focal, plus the training augmentation's roll, focal and principal-point jitter when
``--augment``), the face found and aligned; the table gives the yaw and pitch errors against the
camera asked and how far the aligned crop's landmarks land from where the same head's landmarks sit
in its render at that camera without augmentation (the training framing), in pixels of a 512² crop.

    python bench/face_pose.py [--cases 40] [--resolution 256] [--augment]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import lp3d_render
from lp3d.images import rgb_to_uint8
from lp3d.photo import align_face, find_faces
from lp3d.render.camera import fov_to_focal, look_at_camera
from lp3d.render.native import native_triplane
from lp3d.teachers.procedural import ProceduralTeacher

HELD_OUT_SEED = 1_000_000


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=40)
    p.add_argument("--resolution", type=int, default=256)
    p.add_argument("--augment", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--training-identities",
        action="store_true",
        help="teacher identities of the training range (for tuning) instead of held-out ones",
    )
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    teacher = ProceduralTeacher(version=2)
    r = args.resolution
    rows = []
    missed = 0
    t0 = time.perf_counter()
    for i in range(args.cases):
        tri = native_triplane(teacher.sample((0 if args.training_identities else HELD_OUT_SEED) + i))
        yaw, pitch = float(rng.uniform(-49, 49)), float(rng.uniform(-26, 26))
        plain = look_at_camera(yaw_deg=yaw, pitch_deg=pitch)
        if args.augment:
            cam = look_at_camera(
                yaw_deg=yaw,
                pitch_deg=pitch,
                roll_deg=float(rng.normal(0, 2)),
                focal=fov_to_focal(float(rng.normal(18.83, 1))),
                cx=0.5 + float(rng.normal(0, 14 / 512)),
                cy=0.5 + float(rng.normal(0, 14 / 512)),
            )
            cams = np.stack([cam, plain])
        else:
            cams = plain[None]
        out = lp3d_render.render(tri, cams, resolution=r, outputs=["rgb"])
        imgs = [rgb_to_uint8(x) for x in out["rgb"]]
        faces = find_faces(imgs[0])
        ref_faces = find_faces(imgs[-1])
        if not faces or not ref_faces:
            missed += 1
            continue
        a = align_face(faces[0].landmarks)
        m = a.crop.matrix(r)
        aligned = faces[0].landmarks @ m[:, :2].T + m[:, 2]
        px = np.linalg.norm(aligned - ref_faces[0].landmarks, axis=1).mean() * 512 / r
        rows.append((yaw, pitch, a.yaw_deg - yaw, a.pitch_deg - pitch, px))
    e = np.array(rows)
    print(
        f"{len(rows)} of {args.cases} cases with a face found in both renders ({missed} missed), "
        f"{time.perf_counter() - t0:.0f} s"
    )
    print("| | median | 90th percentile | max |\n|---|---|---|---|")
    for name, col in (("yaw error (°)", 2), ("pitch error (°)", 3), ("framing (px of 512²)", 4)):
        v = np.abs(e[:, col])
        print(f"| {name} | {np.median(v):.1f} | {np.percentile(v, 90):.1f} | {v.max():.1f} |")
    worst = e[np.argsort(-np.abs(e[:, 2]))[:5]]
    for y, pt, dy, dp, px in worst:
        print(f"  worst yaw: asked {y:+.0f}/{pt:+.0f}, error {dy:+.1f}/{dp:+.1f}, framing {px:.1f} px")


if __name__ == "__main__":
    main()
