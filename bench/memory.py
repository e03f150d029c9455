"""Peak device and host memory per frame, against resolution and sample count.

    python bench/memory.py [--markdown] [--resolutions 128 512] [--samples 12+12 48+48 96+96]

Each configuration renders a 256² procedural teacher head (all outputs, one camera) in a fresh
process, so its host peak is its own. Device memory is the sum of the wgpu buffers the renderer
allocates: the triplane's (planes, decoder; ``Triplane.device_bytes``) and the frame's (outputs,
readbacks, uniforms, cameras; ``lp3d_render.last_frame_device_bytes()``). Host memory is the
process's resident-set high-water mark (``ru_maxrss``) after the frame, and before it (after import
and building the triplane), so the difference is what rendering the frame added. On lavapipe
"device" buffers live in host memory too, and the host peak includes the shader compiler's.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.teachers import ProceduralTeacher
r, s, n = (int(a) for a in sys.argv[1:4])
t = ProceduralTeacher().sample(0)
tri = t.to_native()
cam = look_at_camera(yaw_deg=20.0)
lp3d_render.render(tri, cam, resolution=8, depth_resolution=4, depth_resolution_importance=4)  # compile
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
lp3d_render.render(tri, cam, resolution=r, depth_resolution=s, depth_resolution_importance=n)
seconds = time.perf_counter() - start
print(json.dumps({
    "triplane_device": tri.device_bytes,
    "frame_device": lp3d_render.last_frame_device_bytes(),
    "host_before_kib": before,
    "host_peak_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
    "seconds": seconds,
}))
"""


def measure(r: int, s: int, n: int) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(r), str(s), str(n)], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[128, 512])
    parser.add_argument("--samples", nargs="+", default=["12+12", "48+48", "96+96"])
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args(argv)
    mib = 1 << 20
    rows = []
    for r in args.resolutions:
        for spec in args.samples:
            s, n = (int(x) for x in spec.split("+"))
            m = measure(r, s, n)
            rows.append((r, spec, m))
            print(f"R={r} {spec}: {json.dumps(m)}", file=sys.stderr, flush=True)
    if args.markdown:
        print(
            "| R | samples | triplane device MiB | frame device MiB | host before MiB | host peak MiB | s |"
        )
        print("|---|---|---|---|---|---|---|")
        for r, spec, m in rows:
            print(
                f"| {r} | {spec} | {m['triplane_device'] / mib:.2f} | {m['frame_device'] / mib:.2f} | "
                f"{m['host_before_kib'] / 1024:.0f} | {m['host_peak_kib'] / 1024:.0f} | {m['seconds']:.1f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
