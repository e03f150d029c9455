"""``lp3d share``: a triplane file as one self-contained web page that renders it in the browser
(WebGPU) with lp3d's own WGSL kernels (:mod:`lp3d.share`, ``docs/share.md``)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from lp3d.cli.common import (
    Staged,
    angle,
    check_distinct,
    check_output,
    human_bytes,
    image_side,
    load_triplane_file,
    parse_samples,
    say,
)

HELP = "write a triplane as one web page that renders it in the browser (WebGPU)"
DESCRIPTION = (
    "Write one self-contained HTML file holding the triplane, its decoder and lp3d's WGSL render "
    "kernels: open it in a WebGPU browser (no network, no install) to orbit, zoom and reset the head."
)

#: What ``lp3d share`` writes.
PAGE_SUFFIXES = (".html", ".htm")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lp3d.render.settings import RenderSettings

    default = RenderSettings()
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output page (.html)")
    p.add_argument(
        "--resolution",
        type=image_side,
        default=default.resolution,
        help="rays per side of the page's final image (default: %(default)s); the view is scaled to fit",
    )
    p.add_argument(
        "--samples",
        type=parse_samples,
        default=(default.depth_resolution, default.depth_resolution_importance),
        metavar="COARSE+FINE",
        help="samples per ray of the final image (default: 48+48); while the view moves the page "
        "renders cheaper rungs, as lp3d-view does",
    )
    p.add_argument(
        "--float16",
        action="store_true",
        help="store float32 planes as float16: half the size, but the images then differ from the "
        "file's where a surface's edge is sharp (default: the file's precision)",
    )
    p.add_argument(
        "--no-superres",
        action="store_true",
        help="leave the super-resolution network out: by default a head of the shipped model gets it "
        "(its still view super-resolved 64² to 256², about 0.45 MB more page)",
    )
    p.add_argument("--title", default=None, help="the page's title (default: the file's name)")
    p.add_argument("--yaw", type=angle(), default=0.0, help="initial yaw in degrees (default: 0)")
    p.add_argument(
        "--pitch", type=angle(-85.0, 85.0), default=0.0, help="initial pitch in degrees (default: 0)"
    )


def _check_renderable(path: Path, tri: object) -> None:
    """The renderer's own checks of what it would draw (e.g. values that overflow float32 in the
    decoder, which the page would show as a black image): one 1-pixel render."""
    from lp3d.errors import UserError
    from lp3d.render.camera import look_at_camera
    from lp3d.render.native import render

    try:
        render(tri, look_at_camera(), resolution=1, depth_resolution=2, depth_resolution_importance=0)
    except ValueError as e:
        raise UserError(f"{path}: {e}") from None


def run(args: argparse.Namespace) -> int:
    from lp3d.render.settings import RenderSettings
    from lp3d.share import write_page

    out_path = check_output(args.output, PAGE_SUFFIXES)
    check_distinct([("triplane", args.triplane)], [("-o", out_path)])
    tri = load_triplane_file(args.triplane)
    _check_renderable(args.triplane, tri)
    coarse, fine = args.samples
    settings = RenderSettings(
        resolution=args.resolution, depth_resolution=coarse, depth_resolution_importance=fine
    )
    from lp3d.errors import safe_text

    # A name or --title with bytes that are not UTF-8 (or control characters) is shown escaped.
    title = safe_text(args.title if args.title is not None else args.triplane.name)
    start = time.perf_counter()
    superres = None
    if not args.no_superres:
        from lp3d.lift.gpu_superres import shipped_superres_entry, superres_on_gpu

        entry = shipped_superres_entry(tri)
        superres = None if entry is None else superres_on_gpu(entry)
    with Staged() as staged:
        try:
            size = write_page(
                staged.temp(out_path),
                tri,
                title=title,
                settings=settings,
                float16=args.float16,
                yaw_deg=args.yaw,
                pitch_deg=args.pitch,
                superres=superres,
            )
        except ValueError as e:
            from lp3d.errors import UserError

            raise UserError(f"{args.triplane}: {e}") from None
        staged.commit()
    h, w = tri.plane_size
    from lp3d.share import plane_dtype

    dtype = plane_dtype(tri, float16=args.float16)
    network = ", the super-resolution network" if superres is not None else ""
    say(
        f"wrote {out_path} ({human_bytes(size)}: {h}x{w} {dtype} planes, decoder{network}, lp3d's WGSL "
        f"kernels) in {time.perf_counter() - start:.1f} s"
    )
    say(f"open it in a WebGPU browser (Chrome, Edge, Safari; Firefox where enabled): {out_path.resolve()}")
    return 0
