"""``lp3d-view``: the viewer's console script, an alias of ``lp3d view`` (:mod:`lp3d.cli.view` parses
the command line and starts the viewer compiled into ``lp3d_render``)."""

from __future__ import annotations

import sys

from lp3d.cli import standalone_parser
from lp3d.cli import view as _command
from lp3d.cli.common import parse_samples
from lp3d.errors import run_command

__all__ = ["main", "parse_samples"]


def main(argv: list[str] | None = None) -> int:
    return run_command(standalone_parser(_command, "lp3d-view"), argv)


if __name__ == "__main__":
    sys.exit(main())
