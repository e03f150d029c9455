"""``lp3d view`` (also the ``lp3d-view`` console script): the interactive viewer compiled into
``lp3d_render`` (the same Rust code as ``cargo run -p lp3d-viewer``), with the same flags: they are
parsed by the viewer crate (``crates/viewer/src/options.rs``) in both."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from lp3d.cli.common import UsageError, UserError

HELP = "open a triplane file in the interactive viewer"
DESCRIPTION = (
    "Interactive viewer for EG3D-format triplanes (.npz). Drag to orbit, right-drag or shift-drag to pan, "
    "scroll to zoom, double-click to reset; drop a .npz file to open it."
)


#: The viewer's flags are defined once, by the viewer crate's parser (``lp3d_render.view_options``;
#: ``lp3d view --help`` prints its ``VIEW_USAGE``): this parser hands every argument through
#: untouched. NUL cannot occur in a command-line argument, so with it as the only prefix
#: character argparse reads no argument (not even ``-h``) as one of its own options.
PARSER_OPTIONS = {"add_help": False, "prefix_chars": "\0"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "argv", nargs=argparse.REMAINDER, metavar="...", help="[options] [triplane.npz]; --help lists them"
    )


def run(args: argparse.Namespace) -> int:
    import lp3d_render

    try:
        options = lp3d_render.view_options(list(args.argv))
    except ValueError as e:
        raise UsageError(str(e)) from None
    if options.pop("help"):  # the viewer's usage, under the name it was called by (lp3d view)
        print(lp3d_render.VIEW_USAGE.replace("lp3d-view", args.command_parser.prog, 1))
        return 0
    path = options.pop("path")
    if options["superres"] is None and not options["no_superres"] and path is not None:
        options["superres"] = shipped_superres_for(path)
    try:
        lp3d_render.view(path, **options)
    except RuntimeError as e:  # the window system or GPU (ValueError and OSError name their input)
        raise UserError(str(e)) from None
    if options["screenshot"] is not None:
        print(f"wrote {options['screenshot']}")
    return 0


def shipped_superres_for(path: str | os.PathLike[str]) -> Path | None:
    """The shipped model's super-resolution weights file (checked against its SHA-256) when the
    triplane at ``path`` was lifted by it (:func:`lp3d.lift.gpu_superres.shipped_superres_entry`), else
    None; the viewer reads the file itself. A triplane that does not load is left to the viewer, whose
    error names it."""
    from lp3d.lift.gpu_superres import shipped_superres_entry
    from lp3d.lift.model_package import verify_superres_weights
    from lp3d.render.triplane_io import load_triplane

    try:
        tri = load_triplane(path)
    except (OSError, ValueError):
        return None
    entry = shipped_superres_entry(tri)
    if entry is None:
        return None
    verify_superres_weights(entry)
    return entry.weights_path


def main(argv: list[str] | None = None) -> int:
    """``lp3d-view``, the viewer's console script: ``lp3d view`` on its own."""
    import sys

    from lp3d.cli import standalone_parser
    from lp3d.errors import run_command

    return run_command(standalone_parser(sys.modules[__name__], "lp3d-view"), argv)
