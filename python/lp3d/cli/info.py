"""``lp3d info``: what a triplane file holds, as text or JSON."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.cli.common import (
    human_bytes,
    load_triplane_file,
)

HELP = "describe a triplane file"
DESCRIPTION = (
    "Print what a triplane .npz holds: planes, decoder, bounds, camera, "
    "source, occupancy, size and format version."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")


def camera_summary(label: np.ndarray) -> dict[str, float]:
    """A camera label as yaw/pitch of its centre about the origin (as ``look_at_camera`` takes them),
    radius and focal length."""
    c2w = np.asarray(label, np.float64)[:16].reshape(4, 4)
    centre = c2w[:3, 3]
    radius = float(np.linalg.norm(centre))
    yaw = math.degrees(math.atan2(centre[0], centre[2]))
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, centre[1] / radius)))) if radius > 0 else 0.0
    return {"yaw_deg": yaw, "pitch_deg": pitch, "radius": radius, "focal": float(label[16])}


def triplane_info(path: Path) -> dict[str, Any]:
    """Everything ``lp3d info`` prints, as plain data."""
    tri = load_triplane_file(path)
    with np.load(path, allow_pickle=False) as npz:
        version = int(npz["format_version"])
    planes = tri.planes.astype(np.float32)
    info: dict[str, Any] = {
        "file": str(path),
        "file_size": path.stat().st_size,
        "format_version": version,
        "planes": {
            "shape": list(tri.planes.shape),
            "dtype": str(tri.planes.dtype),
            "min": float(planes.min()),
            "max": float(planes.max()),
            "mean": float(planes.mean()),
            "std": float(planes.std()),
            "per_plane_std": [float(planes[p].std()) for p in range(3)],
        },
        "decoder": {
            name: {
                "shape": list(a.shape),
                "min": float(a.min()),
                "max": float(a.max()),
                "mean": float(a.mean()),
                "rms": float(np.sqrt(np.mean(np.square(a, dtype=np.float64)))),
            }
            for name, a in (("w0", tri.w0), ("b0", tri.b0), ("w1", tri.w1), ("b1", tri.b1))
        },
        "box_warp": tri.box_warp,
        "box": [-tri.box_warp / 2.0, tri.box_warp / 2.0],
        "ray_start": tri.ray_start,
        "ray_end": tri.ray_end,
        "camera": None if tri.camera is None else camera_summary(tri.camera),
        "source": tri.source,
        "occupancy": None,
    }
    # A hidden unit does nothing when its input row or its output column is all zeros.
    used = np.abs(tri.w0).sum(axis=1) * np.abs(tri.w1).sum(axis=0)
    info["decoder"]["hidden_units_used"] = int(np.count_nonzero(used))
    info["decoder"]["density_bias"] = float(tri.b1[0])
    if tri.occupancy is not None:
        occ = tri.occupancy
        info["occupancy"] = {
            "shape": list(occ.shape),
            "min": float(occ.min()),
            "max": float(occ.max()),
            "fraction_nonzero": float(np.count_nonzero(occ) / occ.size),
        }
    return info


def run(args: argparse.Namespace) -> int:
    info = triplane_info(args.triplane)
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
    print("\n".join(lines))
    return 0
