"""Errors a user sees, and the one exit-code policy of every lp3d entry point.

``lp3d COMMAND``, ``lp3d-view`` and ``python -m lp3d.train|eval|export|superres_fit|demo`` all end
through :func:`run_command`, so they agree:

* **0** success;
* **1** a runtime error (a bad input file, a failed check, a missing dependency): one line on stderr,
  ``PROG: error: <what and where>``, no traceback (``LP3D_DEBUG=1`` shows it);
* **2** a usage error: argparse's own (an unknown flag, a value out of range) or a :class:`UsageError`
  raised after parsing (flags that exclude each other), printed with the usage line;
* **130** interrupted (Ctrl-C).

This module imports nothing of lp3d, so every module may use it.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Sequence

__all__ = [
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "UsageError",
    "UserError",
    "run_command",
]

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UserError(Exception):
    """A runtime error the user can fix (a bad file, an output that cannot be written, a missing
    optional dependency), printed as one line naming what and where: exit status 1."""


class UsageError(Exception):
    """A usage error found after parsing (flags that exclude each other): argparse's format and exit
    status 2."""


def _format_error(e: BaseException) -> str:
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or e}"
    return str(e) or type(e).__name__


def run_command(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and call ``args.func(args)``, mapping what it raises
    to the exit statuses above; returns the status (it never calls ``sys.exit``).

    A subcommand's parser should ``set_defaults(func=..., command_parser=itself)`` so that its name
    (``lp3d encode``) leads its messages; without ``func`` the parser's help is printed (status 2)."""
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as e:  # --help/--version (0) or a usage error (2); argparse has printed it
        return e.code if isinstance(e.code, int) else (EXIT_OK if e.code is None else EXIT_USAGE)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    command: argparse.ArgumentParser = getattr(args, "command_parser", None) or parser
    try:
        return int(func(args))
    except UsageError as e:
        with contextlib.suppress(SystemExit):  # error() prints the usage line and the message, exits 2
            command.error(str(e))
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{command.prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader of stdout went away (`lp3d info x.npz | head -1`): no message
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so the exit flush is quiet too
        return EXIT_ERROR
    # ValueError covers the library's validation errors (TriplaneError, ModelPackageError, PhotoError,
    # ...), OSError unreadable and unwritable files: all name their input.
    except (UserError, ValueError, OSError) as e:
        if os.environ.get("LP3D_DEBUG"):
            raise
        print(f"{command.prog}: error: {_format_error(e)}", file=sys.stderr)
        return EXIT_ERROR
