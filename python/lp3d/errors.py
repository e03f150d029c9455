"""Errors a user sees, and the one exit-code policy of every lp3d entry point.

``lp3d COMMAND``, ``lp3d-view`` and ``python -m lp3d.train|eval|export|superres_fit|demo`` all end
through :func:`run_command`, so they agree:

* **0** success;
* **1** a runtime error (a bad input file, a failed check, a missing dependency): one line on stderr,
  ``PROG: error: <what and where>``, no traceback (``LP3D_DEBUG=1`` shows it);
* **2** a usage error: argparse's own (an unknown flag, a value out of range) or a :class:`UsageError`
  raised after parsing (flags that exclude each other), printed with the usage line;
* **130** interrupted (Ctrl-C).

When the renderer cannot start (no GPU adapter, a ``WGPU_BACKEND`` or ``LP3D_KERNEL`` it does not know),
every command ends with one line saying what is missing and how to install it
(:func:`renderer_setup_error`), whichever step first touched the GPU.

This module imports nothing of lp3d, so every module may use it.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import sys
from collections.abc import Callable, Sequence

__all__ = [
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "UsageError",
    "UserError",
    "float_in",
    "int_in",
    "renderer_setup_error",
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


# Argparse types every entry point shares: a bad value is a usage error naming its flag
# ("argument --max-steps: must be in [1, 1000000000], got -5", exit 2), found at parse time, before
# any slow work or allocation.


def int_in(lo: int, hi: int) -> Callable[[str], int]:
    """An integer in ``[lo, hi]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:  # also an int of more than 4300 digits: shown cut short
            shown = repr(text) if len(text) <= 40 else f"{text[:20]!r}... ({len(text)} characters)"
            raise argparse.ArgumentTypeError(f"expected an integer, got {shown}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be in [{lo}, {hi}], got {value}")
        return value

    return parse


def float_in(lo: float, hi: float, *, hi_open: bool = False) -> Callable[[str], float]:
    """A finite number in ``[lo, hi]`` (``[lo, hi)`` with ``hi_open``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(value) and lo <= value and (value < hi if hi_open else value <= hi)):
            raise argparse.ArgumentTypeError(
                f"must be in [{lo:g}, {hi:g}{')' if hi_open else ']'}, got {text}"
            )
        return value

    return parse


def _format_error(e: BaseException) -> str:
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or e}"
    text = str(e) or type(e).__name__
    return renderer_setup_error(text) or text


#: wgpu's names for its backends (``wgpu::Backends::from_comma_list``); wgpu skips any other name in
#: ``WGPU_BACKEND`` with a log line, and with none left it finds no adapter.
_WGPU_BACKENDS = frozenset(
    {"vulkan", "vk", "dx12", "d3d12", "metal", "mtl", "opengl", "gles", "gl", "webgpu", "noop"}
)
_INSTALL_DRIVER = (
    "the renderer needs a Vulkan, Metal or DirectX 12 driver; on Linux without a GPU install Mesa's "
    "lavapipe (sudo apt install mesa-vulkan-drivers libvulkan1, or scripts/install-system-deps.sh) "
    "and set WGPU_BACKEND=vulkan"
)


def _no_adapter_reasons(message: str) -> list[str]:
    """What the renderer's "no usable GPU adapter (...)" says about each backend it tried (wgpu's
    "vulkan drivers/libraries could not be loaded"; backends not asked for are left out), and an ICD
    file named in ``VK_DRIVER_FILES``/``VK_ICD_FILENAMES`` that does not exist."""
    found = re.search(r"No suitable graphics adapter found; (.*?)\); adapters seen", message)
    reasons = [r.strip() for r in found.group(1).split(",")] if found else []
    reasons = [r for r in reasons if r and not r.endswith("not requested")]
    for var in ("VK_DRIVER_FILES", "VK_ICD_FILENAMES"):
        missing = [f for f in os.environ.get(var, "").split(os.pathsep) if f and not os.path.exists(f)]
        reasons += [f"{var} names {f}, which does not exist" for f in missing]
    seen = re.search(r"adapters seen: (\[[^\]]+\])", message)
    if seen:
        reasons.append(f"adapters seen: {seen.group(1)}")
    return reasons


def renderer_setup_error(message: str) -> str | None:
    """The one line a user sees when ``message`` (an error's text) says the renderer ``lp3d_render``
    cannot start, else None: no usable GPU adapter (``crates/renderer/src/device.rs``: the most common
    first-run failure), a ``WGPU_BACKEND`` that names no backend, an ``LP3D_KERNEL`` the renderer does
    not know (``crates/renderer/src/kernel.rs``), or another GPU failure (``GPU error: ...``, already
    one line). The renderer raises these as ``RuntimeError`` from whichever call first needs the GPU,
    so they are recognised here, where every entry point ends (:func:`run_command`)."""
    if "LP3D_KERNEL: must be" in message:
        value = os.environ.get("LP3D_KERNEL", "")
        return (
            f"the environment variable LP3D_KERNEL={value!r} names no renderer kernel: set it to auto, "
            "fast or quick, or unset it"
        )
    no_adapter = "no usable GPU adapter" in message
    no_surface = "Failed to create surface for any enabled backend" in message  # the viewer's window
    if no_adapter or no_surface:
        backend = os.environ.get("WGPU_BACKEND", "")
        names = [b.strip().lower() for b in backend.split(",") if b.strip()]
        if names and not set(names) & _WGPU_BACKENDS:
            return (
                f"the environment variable WGPU_BACKEND={backend!r} names no GPU backend: set it to vulkan, "
                "metal, dx12 or gl, or unset it"
            )
        reasons = _no_adapter_reasons(message) if no_adapter else [" ".join(message.split())]
        why = f" ({'; '.join(reasons)})" if reasons else ""
        return f"no GPU adapter{why}: {_INSTALL_DRIVER}"
    if message.startswith("GPU error: "):
        return " ".join(message.split())
    return None


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
    except RuntimeError as e:  # the renderer's: no GPU adapter, a bad WGPU_BACKEND or LP3D_KERNEL
        line = renderer_setup_error(str(e))
        if line is None or os.environ.get("LP3D_DEBUG"):
            raise
        print(f"{command.prog}: error: {line}", file=sys.stderr)
        return EXIT_ERROR
