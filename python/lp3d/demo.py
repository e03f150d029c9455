"""``python -m lp3d.demo``: an alias of ``lp3d demo`` (photo in, 3D out, with the shipped model). The
demo itself is :mod:`lp3d.cli.demo`; its names stay importable from here."""

from __future__ import annotations

import sys

from lp3d.cli import demo as _command
from lp3d.cli import standalone_parser
from lp3d.cli.demo import (
    ORBIT_BATCH,
    TEACHER_SEED,
    VIEW_YAWS,
    Portrait,
    add_arguments,
    astronaut_portrait,
    run,
    teacher_portrait,
)
from lp3d.errors import run_command

__all__ = [
    "ORBIT_BATCH",
    "TEACHER_SEED",
    "VIEW_YAWS",
    "Portrait",
    "add_arguments",
    "astronaut_portrait",
    "main",
    "run",
    "teacher_portrait",
]


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.demo`` is ``lp3d demo``."""
    return run_command(standalone_parser(_command, "python -m lp3d.demo"), argv)


if __name__ == "__main__":
    sys.exit(main())
