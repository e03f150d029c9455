"""``lp3d``: the command line. One entry point, one subcommand per job::

    lp3d encode photo.jpg -o head.npz            photo(s) -> triplane(s) (face detection + alignment)
    lp3d render head.npz --yaw 30 -o view.png    one view (also --depth, --features-channel)
    lp3d orbit head.npz -o orbit.mp4             a turntable video (.gif or .mp4)
    lp3d mesh head.npz -o head.glb               marching cubes (.ply, .obj or .glb)
    lp3d share head.npz -o head.html             one web page that renders it in the browser (WebGPU)
    lp3d serve                                   a local web app: photo or webcam in, live 3D head out
    lp3d info head.npz                           what is in a triplane file
    lp3d video in.mp4 -o out.mp4 --yaw 20        lift a talking-head video frame by frame
    lp3d view head.npz                           the interactive viewer (also: lp3d-view)
    lp3d demo                                    the end-to-end demo
    lp3d train | eval | export | superres-fit    training and its tools (need torch; python -m lp3d.train)
    lp3d eval-photos photos/ --out report/       identity and pose of lifted real photos (needs torch)

**Super-resolution.** When the model package has a super-resolution network (SR; see
``docs/model-package.md``), ``render``, ``orbit``, ``video`` and ``demo`` draw the raw feature image at
the network's input size and write the super-resolved image at its output size (``--resolution``
resizes that); ``--raw`` gives the plain volume render instead. ``video`` and ``demo`` use their
``--model``'s SR. A triplane file names no model, so ``render`` and ``orbit`` apply the SR of
``--model MODEL`` when given (an error if that package has none, or if the triplane's decoder and
bounds are not that package's), else the shipped model's SR when the triplane has the shipped model's
decoder and bounds (every triplane the shipped model encodes has), else none (raw, and they say why).

Every subcommand has ``--help`` and is one module of this package (``add_arguments(parser)``,
``run(args) -> int``, optionally ``PARSER_OPTIONS`` for its argparse parser: ``view`` hands its
arguments to the viewer crate's own parser); what they share is in :mod:`lp3d.cli.common`. Errors go
to stderr as ``lp3d <command>: error: <what and where>``: exit status 0 ok, 1 an error, 2 a usage error, 130
interrupted (:mod:`lp3d.errors`, the policy of every entry point); set ``LP3D_DEBUG=1`` for the
traceback. Outputs are written to temporary files beside their destination and renamed into place
only when everything succeeded (:mod:`lp3d.outputs`), so a failed command leaves no partial files;
an output that would replace an input or another output (by name, relative path or link) is refused
before any work. Rendering uses ``lp3d_render`` (wgpu); on a machine without a GPU set
``VK_DRIVER_FILES`` to Mesa's lavapipe ICD (see README).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from lp3d.cli import _startup  # noqa: F401  (first: Ctrl-C during the imports below)
from lp3d.cli.common import PROG
from lp3d.errors import EXIT_ERROR, run_command

__all__ = ["COMMANDS", "build_parser", "main", "standalone_parser"]

#: The subcommands in ``lp3d --help`` order: each module has ``HELP``, ``add_arguments(parser)`` and
#: ``run(args) -> int``, and ``DESCRIPTION`` unless its ``add_arguments`` sets it; ``LAZY`` ones import
#: torch, so their options are added only when the command line names them.
COMMANDS: dict[str, ModuleType] = {
    name: importlib.import_module(f"lp3d.cli.{name.replace('-', '_')}")
    for name in (
        "encode",
        "render",
        "orbit",
        "mesh",
        "share",
        "serve",
        "info",
        "video",
        "view",
        "demo",
        "train",
        "eval",
        "eval-photos",
        "export",
        "superres-fit",
    )
}


def _add_command(p: argparse.ArgumentParser, module: ModuleType) -> None:
    module.add_arguments(p)
    p.set_defaults(func=module.run, command_parser=p)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``lp3d`` parser. A lazy subcommand (train, eval, export, superres-fit) gets its options only when
    ``command`` names it, so that ``lp3d encode`` never imports torch."""
    from lp3d import __version__ as version

    parser = argparse.ArgumentParser(
        prog=PROG,
        description="lp3d: single portrait photo -> 3D (EG3D triplane), rendered in real time.",
        epilog="Run 'lp3d COMMAND --help' for each command's options.",
    )
    parser.add_argument("--version", action="version", version=f"lp3d {version}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in COMMANDS.items():
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=getattr(module, "DESCRIPTION", None),
            **getattr(module, "PARSER_OPTIONS", {}),
        )
        if not getattr(module, "LAZY", False) or name == command:
            _add_command(p, module)
    return parser


def standalone_parser(module: ModuleType, prog: str) -> argparse.ArgumentParser:
    """A parser for one subcommand on its own (``lp3d-view``), to run with
    :func:`lp3d.errors.run_command`."""
    p = argparse.ArgumentParser(
        prog=prog, description=getattr(module, "DESCRIPTION", None), **getattr(module, "PARSER_OPTIONS", {})
    )
    _add_command(p, module)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 error, 2 usage, 130 interrupted)."""
    args = sys.argv[1:] if argv is None else list(argv)
    command = args[0] if args else None
    try:
        parser = build_parser(command)
    except ModuleNotFoundError as e:  # a lazy subcommand without its dependencies (torch)
        print(
            f"{PROG} {command}: error: {e}; install the training extra: pip install 'lp3d[train]'",
            file=sys.stderr,
        )
        return EXIT_ERROR
    except ImportError as e:  # installed, but a library did not load (a memory limit, a broken install)
        print(f"{PROG} {command}: error: a library could not be loaded: {e}", file=sys.stderr)
        return EXIT_ERROR
    return run_command(parser, args)
