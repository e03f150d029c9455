"""``lp3d info``: what a triplane file holds, as text or JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lp3d.cli.common import human_bytes
from lp3d.errors import UserError, safe_text
from lp3d.render.triplane_io import triplane_info

HELP = "describe a triplane file"
DESCRIPTION = (
    "Print what a triplane .npz holds: planes, decoder, bounds, camera, "
    "source, occupancy, size and format version."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")


def run(args: argparse.Namespace) -> int:
    try:
        info = triplane_info(args.triplane)
    except FileNotFoundError:
        raise UserError(f"{args.triplane}: no such file") from None
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    p, d = info["planes"], info["decoder"]
    lines = [
        f"file:           {info['file']} ({human_bytes(info['file_size'])}, "
        f"format_version {info['format_version']})",
        f"planes:         {tuple(p['shape'])} {p['dtype']}  (3 planes x 32 channels x "
        f"{p['shape'][2]}x{p['shape'][3]})",
        f"  values:       min {p['min']:.4g}, max {p['max']:.4g}, mean {p['mean']:.4g}, std {p['std']:.4g}; "
        f"std per plane {', '.join(f'{s:.3g}' for s in p['per_plane_std'])}",
        f"decoder:        w0 {tuple(d['w0']['shape'])}, b0 {tuple(d['b0']['shape'])}, "
        f"w1 {tuple(d['w1']['shape'])}, b1 {tuple(d['b1']['shape'])}; "
        f"{d['hidden_units_used']} of {d['w0']['shape'][0]} hidden units used",
    ]
    for name in ("w0", "b0", "w1", "b1"):
        s = d[name]
        lines.append(
            f"  {name}:           min {s['min']:.4g}, max {s['max']:.4g}, mean {s['mean']:.4g}, "
            f"rms {s['rms']:.4g}"
        )
    lines.append(f"  density bias: b1[0] = {d['density_bias']:.4g} (raw density output)")
    lines += [
        f"box:            [{info['box'][0]:g}, {info['box'][1]:g}]^3 (box_warp {info['box_warp']:g})",
        f"rays:           t in [{info['ray_start']:g}, {info['ray_end']:g}]",
    ]
    cam = info["camera"]
    lines.append(
        "camera:         none (the input view is not stored)"
        if cam is None
        else f"camera:         yaw {cam['yaw_deg']:+.1f}°, pitch {cam['pitch_deg']:+.1f}°, "
        f"radius {cam['radius']:.3g}, focal {cam['focal']:.4g}"
    )
    lines.append(f"source:         {info['source'] if info['source'] is not None else 'none'}")
    occ = info["occupancy"]
    lines.append(
        "occupancy:      none (not baked)"
        if occ is None
        else f"occupancy:      {tuple(occ['shape'])} grid, {100 * occ['fraction_nonzero']:.1f}% non-zero, "
        f"range [{occ['min']:.3g}, {occ['max']:.3g}]"
    )
    # The file's name and its strings (source) are the file's author's: escaped, so that they
    # cannot reach the terminal as escape sequences or forge a line of this output.
    print("\n".join(safe_text(line) for line in lines))
    return 0
