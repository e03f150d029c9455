"""Errors a user sees, and the one exit-code policy of every lp3d entry point.

``lp3d COMMAND``, ``lp3d-view`` and ``python -m lp3d.train|export|superres_fit`` all end
through :func:`run_command`, so they agree:

* **0** success;
* **1** a runtime error (a bad input file, a failed check, a missing dependency): one line on stderr,
  ``PROG: error: <what and where>``, no traceback (``LP3D_DEBUG=1`` shows it);
* **2** a usage error: argparse's own (an unknown flag, a value out of range) or a :class:`UsageError`
  raised after parsing (flags that exclude each other), printed with the usage line;
* **130** interrupted (Ctrl-C), with one line ``PROG: interrupted``, also during start-up (the imports
  before a command runs: :func:`quiet_startup_interrupts`);
* **143** terminated (SIGTERM), with one line ``PROG: terminated``;
* **141** the reader of stdout went away (``lp3d info x.npz | head -1``: EPIPE), quietly: what a shell
  reports for a process that SIGPIPE ended, as ``cat`` or ``yes`` would be (Python ignores SIGPIPE, so
  the error is caught instead). A stdout that is closed before the command starts (``>&-``) is an
  error (status 1, one line): the command's results would be lost without a word.

While a command runs, SIGTERM raises :class:`Terminated` (a ``BaseException``, like Ctrl-C's
``KeyboardInterrupt``) in the main thread, so every ``finally`` and every atomic writer
(:mod:`lp3d.atomic`) cleans up: a killed command leaves no temporary file. Its output streams never
fail on a character the terminal's encoding lacks (``PYTHONIOENCODING=ascii`` and a path or a ``²``):
such characters are written as backslash escapes.

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
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence

__all__ = [
    "EXIT_BROKEN_PIPE",
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_TERMINATED",
    "EXIT_USAGE",
    "Terminated",
    "UsageError",
    "UserError",
    "MIN_ADDRESS_SPACE",
    "address_space_left",
    "float_in",
    "int_in",
    "quiet_startup_interrupts",
    "renderer_setup_error",
    "run_command",
    "safe_text",
]

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 128 + 15  # 128 + SIGTERM, as a shell reports a process that SIGTERM ended
EXIT_BROKEN_PIPE = 128 + 13  # 128 + SIGPIPE


class UserError(Exception):
    """A runtime error the user can fix (a bad file, an output that cannot be written, a missing
    optional dependency), printed as one line naming what and where: exit status 1."""


class UsageError(Exception):
    """A usage error found after parsing (flags that exclude each other): argparse's format and exit
    status 2."""


class Terminated(BaseException):
    """SIGTERM arrived while a command ran (:func:`run_command`). A ``BaseException``, like
    ``KeyboardInterrupt``, so that ``except Exception`` does not swallow it and every ``finally`` and
    atomic writer on the way out cleans up."""


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


# ------------------------------------------------------------------------------------ text


#: What :func:`safe_text` escapes: C0 and C1 controls, DEL, line and paragraph separators, the bidi
#: overrides and isolates (they reorder what a terminal shows), and lone surrogates (not text at all;
#: U+DC80-U+DCFF are the bytes ``os.fsdecode`` could not decode).
_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069\ud800-\udfff]")


def _escape(char: str) -> str:
    code = ord(char)
    if 0xDC80 <= code <= 0xDCFF:  # a byte of a file name that was not valid UTF-8: show the byte
        return f"\\x{code - 0xDC00:02x}"
    return {"\n": "\\n", "\r": "\\r", "\t": "\\t"}.get(char) or (
        f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"
    )


def safe_text(text: str | bytes | os.PathLike[str] | os.PathLike[bytes]) -> str:
    """``text`` (a string, or a path or file name in any form) as one line that is safe to print, to
    store in a file and to embed in a page: the one policy for every name and every string that came
    from a file or the command line. Names are decoded as Python decodes them (``os.fsdecode``); a
    byte that is not valid UTF-8 becomes ``\\xNN``, control characters (escape sequences, newlines
    that would forge an output line), bidi overrides and lone surrogates become ``\\n``, ``\\x1b``,
    ``\\u202e``. Printable text, non-ASCII included, is kept as it is."""
    if not isinstance(text, str):
        text = os.fsdecode(text)
    return _UNSAFE.sub(lambda m: _escape(m.group()), text)


def _format_error(e: BaseException) -> str:
    if isinstance(e, OSError) and e.filename is not None:
        return safe_text(f"{e.filename}: {e.strerror or e}")
    text = str(e) or type(e).__name__
    return safe_text(renderer_setup_error(text) or text)


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


#: The least address space (``ulimit -v``) a command starts with: below it OpenCV's import crashed
#: (SIGSEGV), and the GPU driver maps most of it again when it starts (``lp3d_render`` checks that
#: then, with its own twin of :func:`address_space_left`: it does not import lp3d).
MIN_ADDRESS_SPACE = 768 << 20


def address_space_left() -> int | None:
    """Bytes this process may still map under its address-space limit (``ulimit -v``), or None when
    it has none (or the platform does not say)."""
    try:
        import resource
    except ImportError:
        return None
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/statm") as f:
            mapped = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None
    return soft - mapped


def renderer_setup_error(message: str) -> str | None:
    """The one line a user sees when ``message`` (an error's text) says the renderer ``lp3d_render``
    cannot start, else None: no usable GPU adapter (``crates/renderer/src/device.rs``: the most common
    first-run failure), a ``WGPU_BACKEND`` that names no backend, an ``LP3D_KERNEL`` the renderer does
    not know (``crates/renderer/src/kernel.rs``), an ``LP3D_FULL_WALK`` other than 0 or 1, or another
    GPU failure (``GPU error: ...``, already one line). The renderer raises these as ``RuntimeError``
    from whichever call first needs the GPU, so they are recognised here, where every entry point ends
    (:func:`run_command`)."""
    if "LP3D_KERNEL: must be" in message:
        value = os.environ.get("LP3D_KERNEL", "")
        return (
            f"the environment variable LP3D_KERNEL={value!r} names no renderer kernel: set it to auto, "
            "fast or quick, or unset it"
        )
    if "LP3D_FULL_WALK: must be" in message:
        value = os.environ.get("LP3D_FULL_WALK", "")
        return (
            f"the environment variable LP3D_FULL_WALK={value!r} is not 0 or 1: set it to 1 to walk every "
            "sample (the outputs are the same; for tests and benchmarks), or unset it"
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


# ------------------------------------------------------------------------------------ signals


def _interrupted_at_startup(signum: int, frame: object) -> None:
    """SIGINT before a command runs: nothing is written yet, so end at once, with one line (a
    traceback from whichever import it hit is noise; numpy even turns it into an ImportError about
    "PyCapsule_Import")."""
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] != "-m" else "lp3d"
    with contextlib.suppress(OSError):
        os.write(2, f"{name}: interrupted\n".encode(errors="replace"))
    os._exit(EXIT_INTERRUPTED)


def quiet_startup_interrupts() -> None:
    """Make Ctrl-C during start-up (the imports before :func:`run_command`: numpy, torch, the renderer)
    end the process with one line and status 130, no traceback. Called first thing by the command
    line's package; acts only in the command-line process itself (``python -m ...`` or the ``lp3d``
    and ``lp3d-view`` scripts), in its main thread, and while Python's own SIGINT handler is in place:
    a program that imports lp3d keeps its own handling. :func:`run_command` restores Python's handler
    (``KeyboardInterrupt``) before it parses the arguments."""
    argv0 = sys.argv[0] if sys.argv else ""
    if argv0 != "-m" and os.path.basename(argv0) not in ("lp3d", "lp3d-view"):
        return
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _interrupted_at_startup)


#: Ctrl-Cs seen while a command runs. An import interrupted by one may fail as an ImportError
#: (numpy's "PyCapsule_Import"), which the code around it reports as a missing package; an error
#: that follows a Ctrl-C is reported as the interrupt instead.
_interrupts = [0]


def _interrupt(signum: int, frame: object) -> None:
    _interrupts[0] += 1
    raise KeyboardInterrupt


def _terminate(signum: int, frame: object) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
    raise Terminated


@contextlib.contextmanager
def _command_signals() -> Iterator[None]:
    """While a command runs (main thread only): Ctrl-C raises ``KeyboardInterrupt`` (counted by
    :func:`_interrupt`, replacing :func:`quiet_startup_interrupts`' handler), and SIGTERM raises
    :class:`Terminated` unless someone else already handles it; the previous handlers are restored
    after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old_int, old_term = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    if old_int is _interrupted_at_startup:
        old_int = signal.default_int_handler
    if old_int is signal.default_int_handler:
        signal.signal(signal.SIGINT, _interrupt)  # KeyboardInterrupt, counted
    if old_term == signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)


def _tolerant_streams() -> None:
    """Output that cannot be encoded (``PYTHONIOENCODING=ascii`` or a C locale, and a path with
    ``é`` or a ``²``) is written with backslash escapes instead of failing the command after its work
    is done. stderr already does this by default; stdout and stderr both get it here."""
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None and getattr(stream, "errors", None) == "strict":
            with contextlib.suppress(ValueError, OSError):  # a closed or detached stream
                reconfigure(errors="backslashreplace")


def _interrupted_or(before: int, func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """``func(args)``; an error it raises after a Ctrl-C arrived (``before``: the count at its start)
    is the interrupt, not what the interrupted code made of it."""
    try:
        return int(func(args))
    except Exception:
        if _interrupts[0] != before:
            raise KeyboardInterrupt from None
        raise


def _stdout_broken() -> bool:
    """Whether stdout is a pipe whose reader has gone (POLLERR on its descriptor)."""
    try:
        import select

        poll = select.poll()
        poll.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poll.poll(0))
    except (AttributeError, OSError, ValueError):  # no poll on this platform, or no stdout
        return True


def run_command(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and call ``args.func(args)``, mapping what it raises
    to the exit statuses above; returns the status (it never calls ``sys.exit``).

    A subcommand's parser should ``set_defaults(func=..., command_parser=itself)`` so that its name
    (``lp3d encode``) leads its messages; without ``func`` the parser's help is printed (status 2)."""
    _tolerant_streams()
    if sys.stdout is None:  # started with stdout closed (`>&-`): nothing it prints could be seen
        if sys.stderr is not None:
            print(f"{parser.prog}: error: stdout is closed; send it to /dev/null instead", file=sys.stderr)
        return EXIT_ERROR
    prog = [parser.prog]  # the command's name once it is known, for the interrupted/terminated line
    with _command_signals():
        try:
            return _run(parser, argv, prog)
        except KeyboardInterrupt:
            print(f"{prog[0]}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except Terminated:
            print(f"{prog[0]}: terminated", file=sys.stderr)
            return EXIT_TERMINATED


def _run(parser: argparse.ArgumentParser, argv: Sequence[str] | None, prog: list[str]) -> int:
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as e:  # --help/--version (0) or a usage error (2); argparse has printed it
        return e.code if isinstance(e.code, int) else (EXIT_OK if e.code is None else EXIT_USAGE)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    command: argparse.ArgumentParser = getattr(args, "command_parser", None) or parser
    prog[0] = command.prog
    left = address_space_left()
    if left is not None and left < MIN_ADDRESS_SPACE:  # the native libraries would crash, not fail
        print(
            f"{command.prog}: error: the address-space limit (ulimit -v) leaves {max(left, 0) >> 20} MiB; "
            f"lp3d's native libraries need at least {MIN_ADDRESS_SPACE >> 20} MiB to start; raise the limit",
            file=sys.stderr,
        )
        return EXIT_ERROR
    interrupts = _interrupts[0]
    try:
        return _interrupted_or(interrupts, func, args)
    except UsageError as e:
        with contextlib.suppress(SystemExit):  # error() prints the usage line and the message, exits 2
            command.error(str(e))
        return EXIT_USAGE
    except BrokenPipeError as e:  # the reader of stdout went away (`lp3d info x.npz | head -1`): quiet
        if not _stdout_broken():  # another pipe (ffmpeg's): an error like any other
            print(f"{command.prog}: error: {_format_error(e)}", file=sys.stderr)
            return EXIT_ERROR
        with contextlib.suppress(OSError, ValueError):  # so the exit flush is quiet too
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
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
