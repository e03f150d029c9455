"""``lp3d mesh``: a coloured mesh (.ply, .obj, .glb) of a triplane file by marching cubes."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from lp3d.cli.common import (
    MESH_SUFFIXES,
    Staged,
    check_distinct,
    check_output,
    float_in,
    human_bytes,
    int_in,
    load_triplane_file,
    say,
)

HELP = "extract a coloured mesh (.ply, .obj, .glb) with marching cubes"
DESCRIPTION = (
    "Sample the decoder's raw density on a grid inside the triplane box, "
    "run marching cubes and colour the vertices with the decoder's RGB."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lp3d.render.mesh import EG3D_MESH_THRESHOLD

    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output mesh (.ply, .obj or .glb)")
    p.add_argument("--grid", type=int_in(8, 512), default=128, help="grid points per axis (default: 128)")
    p.add_argument(
        "--threshold",
        type=float_in(-1e30, 1e30),
        default=EG3D_MESH_THRESHOLD,
        help="raw density level of the surface (default: %(default)s, as EG3D)",
    )
    p.add_argument("--ascii", action="store_true", help="ASCII instead of binary PLY")


def run(args: argparse.Namespace) -> int:
    out_path = check_output(args.output, MESH_SUFFIXES)
    check_distinct([("triplane", args.triplane)], [("-o", out_path)])
    tri = load_triplane_file(args.triplane)
    from lp3d.render.mesh import extract_mesh, write_mesh

    start = time.perf_counter()
    mesh = extract_mesh(tri, grid=args.grid, threshold=args.threshold)
    seconds = time.perf_counter() - start
    with Staged() as staged:
        write_mesh(staged.temp(out_path), mesh, fmt=out_path.suffix, ascii_ply=args.ascii)
        staged.commit()
    say(
        f"marching cubes on a {args.grid}³ density grid at threshold {args.threshold:g}: "
        f"{len(mesh.vertices):,} vertices, {len(mesh.faces):,} triangles in {seconds:.1f} s"
    )
    say(f"wrote {out_path} ({human_bytes(out_path.stat().st_size)})")
    return 0
