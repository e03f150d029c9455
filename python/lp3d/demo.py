"""The main job on the embedded default: build a sample triplane, write it as a `.npz`, render it
from three yaws with its depth map through lp3d_render, and write a PNG.

    python -m lp3d.demo --out demo_out

(The trained-encoder demo, photo in and 3D out, replaces this once the shipped model exists.)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lp3d.demo", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", type=Path, default=Path("demo_out"), help="output folder (default: %(default)s)"
    )
    parser.add_argument("--resolution", type=int, default=128, help="rays per image side (default: 128)")
    args = parser.parse_args(argv)

    import lp3d_render
    from lp3d.camera import look_at_camera
    from lp3d.images import depth_to_uint8, rgb_to_uint8, save_png, tile
    from lp3d.sample_scenes import coloured_sphere
    from lp3d.triplane_io import save_triplane

    info = lp3d_render.adapter_info()
    print(f"renderer: {info['name']} ({info['backend']}, {info['device_type']})")
    scene = coloured_sphere()
    args.out.mkdir(parents=True, exist_ok=True)
    tri_path = args.out / "sphere.npz"
    save_triplane(tri_path, scene)
    tri = lp3d_render.Triplane.load(tri_path)
    yaws = (-40.0, 0.0, 40.0)
    cams = np.stack([look_at_camera(yaw_deg=y, lookat=(0.0, 0.0, 0.0)) for y in yaws])
    start = time.perf_counter()
    out = lp3d_render.render(tri, cams, resolution=args.resolution)
    ms = (time.perf_counter() - start) * 1e3
    print(
        f"rendered {len(yaws)} views at {args.resolution}² (48+48 samples) in {ms:.0f} ms "
        "(the first call in a process includes shader compilation)"
    )
    images = [rgb_to_uint8(rgb) for rgb in out["rgb"]]
    images.append(depth_to_uint8(out["depth"][1], out["weights_sum"][1]))
    png = save_png(args.out / "sphere_views.png", tile(images, columns=4))
    views = ", ".join(f"{y:+.0f}°" for y in yaws)
    print(f"wrote {tri_path}\nwrote {png}  (yaw {views}, then the frontal depth)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
