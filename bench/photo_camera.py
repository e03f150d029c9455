"""The photo's camera as ``lp3d encode --refine`` finds it, three ways, on held-out teacher heads rendered
at known cameras (yaw ±49°, pitch ±26°) and lifted by the shipped encoder:

* ``grid + fit``: the photometric grid search over the lifted head's renders, then the photometric
  fit of a small camera move (lp3d.lift.pose.find_camera);
* ``landmarks``: the pose of the face's five landmarks (lp3d.photo.align_face);
* ``landmarks + fit``: the photometric fit started from the landmarks' pose.

    python bench/photo_camera.py [--cases 20]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import lp3d_render
from lp3d.images import rgb_to_uint8
from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
from lp3d.lift.pose import camera_at, find_camera, fit_pose
from lp3d.lift.refine_settings import RefineSettings
from lp3d.photo import align_face, find_faces, to_encoder_input
from lp3d.render.camera import camera_summary, look_at_camera
from lp3d.render.native import native_triplane
from lp3d.teachers.procedural import ProceduralTeacher

HELD_OUT_SEED = 1_000_000


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=20)
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    teacher = ProceduralTeacher(version=2)
    encoder = load_encoder(DEFAULT_MODEL)
    pkg = encoder.package
    settings = RefineSettings()
    errors: dict[str, list[tuple[float, float]]] = {"grid + fit": [], "landmarks": [], "landmarks + fit": []}
    t0 = time.perf_counter()
    for i in range(args.cases):
        truth = teacher.sample(HELD_OUT_SEED + 100 + i)
        yaw, pitch = float(rng.uniform(-49, 49)), float(rng.uniform(-26, 26))
        out = lp3d_render.render(
            native_triplane(truth),
            look_at_camera(yaw_deg=yaw, pitch_deg=pitch),
            resolution=pkg.image_size,
            outputs=["rgb"],
        )
        img = rgb_to_uint8(out["rgb"])
        faces = find_faces(img)
        if not faces:
            continue
        x = to_encoder_input(img[None])
        tri = pkg.triplane(encoder.encode(x)[0])
        planes = torch.from_numpy(np.asarray(tri.planes, np.float32))
        dec = tuple(
            torch.from_numpy(np.asarray(getattr(tri, k), np.float32)) for k in ("w0", "b0", "w1", "b1")
        )
        a = align_face(faces[0].landmarks)
        found = {
            "grid + fit": find_camera(planes, dec, tri.bounds, x[0], settings),
            "landmarks": camera_at(a.yaw_deg, a.pitch_deg),
            "landmarks + fit": fit_pose(
                planes, dec, tri.bounds, x[0], camera_at(a.yaw_deg, a.pitch_deg), settings
            ),
        }
        for name, cam in found.items():
            s = camera_summary(cam.double().numpy())
            errors[name].append((s["yaw_deg"] - yaw, s["pitch_deg"] - pitch))
    n = len(errors["landmarks"])
    print(f"{n} of {args.cases} held-out heads with a face found, {time.perf_counter() - t0:.0f} s")
    print("| camera | yaw error median / p90 (°) | pitch error median / p90 (°) |\n|---|---|---|")
    for name, e in errors.items():
        v = np.abs(np.array(e))
        print(
            f"| {name} | {np.median(v[:, 0]):.1f} / {np.percentile(v[:, 0], 90):.1f} | "
            f"{np.median(v[:, 1]):.1f} / {np.percentile(v[:, 1], 90):.1f} |"
        )


if __name__ == "__main__":
    main()
