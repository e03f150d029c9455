"""``lp3d render``: one view of a triplane file to an image (also its depth map or a feature channel)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from lp3d.cli.common import (
    IMAGE_SUFFIXES,
    Staged,
    camera_args,
    check_distinct,
    check_output,
    choose_superres,
    describe_size,
    final_images,
    int_in,
    make_camera,
    render_args,
    render_file_views,
    render_triplane_file,
    resize_image,
    say,
    superres_model_arg,
    write_image,
)

HELP = "render one view of a triplane to an image"
DESCRIPTION = "Render one view of a triplane .npz to a PNG/JPEG image."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output image (.png, .jpg)")
    camera_args(p)
    render_args(p, 256)
    p.add_argument("--depth", type=Path, default=None, help="also write the depth map (near = bright) here")
    p.add_argument(
        "--features-channel",
        type=int_in(0, 31),
        default=None,
        metavar="K",
        help="write decoder feature channel K (0-31, grayscale) of the raw render instead of the image",
    )
    superres_model_arg(p)


def run(args: argparse.Namespace) -> int:
    out_path = check_output(args.output, IMAGE_SUFFIXES)
    depth_path = check_output(args.depth, IMAGE_SUFFIXES, "--depth") if args.depth else None
    outputs = [("-o", out_path)] + ([("--depth", depth_path)] if depth_path is not None else [])
    check_distinct([("triplane", args.triplane)], outputs)
    tri, rtri = render_triplane_file(args.triplane)
    from lp3d.images import depth_to_uint8

    camera = make_camera(args)[None]
    extra = ["depth", "weights_sum"] if depth_path is not None else []
    start = time.perf_counter()
    if args.features_channel is not None:
        # A feature channel is a raw quantity: never super-resolved.
        sr, how = None, "raw volume render"
        size = args.resolution or 256
        out = render_file_views(args.triplane, rtri, camera, args, ["features", *extra], resolution=size)
        channel = out["features"][0, args.features_channel]
        image = np.round((np.clip(channel, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    else:
        sr, how = choose_superres(args, tri)
        size = args.resolution or (sr.output_resolution if sr is not None else 256)
        images, out = final_images(rtri, camera, args, sr, size, path=args.triplane, extra=extra)
        image = images[0]
    seconds = time.perf_counter() - start
    with Staged() as staged:
        write_image(staged.temp(out_path), image, out_path.suffix)
        if depth_path is not None:
            depth = depth_to_uint8(out["depth"][0], out["weights_sum"][0])
            write_image(staged.temp(depth_path), resize_image(depth, size), depth_path.suffix)
        written = staged.commit()
    coarse, fine = args.samples
    what = f"feature channel {args.features_channel}" if args.features_channel is not None else "rgb"
    say(
        f"rendered {describe_size(sr, size)} ({coarse}+{fine} samples, yaw {args.yaw:+g}°, pitch "
        f"{args.pitch:+g}°, {what}; {how}) in {seconds:.2f} s"
    )
    for path in written:
        say(f"wrote {path}")
    return 0
