"""The ``lp3d`` command line as a whole, run in-process through ``lp3d.cli.main``: help for every
command, the ``python -m`` entry points, one exit-code policy, the import graph, usage errors.

Fixtures (a sample triplane, a tiny model, test photos) are in ``tests/cli/conftest.py``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from support.cli import run


def test_help_for_every_command(capsys) -> None:
    code, out, _ = run(capsys, "--help")
    assert code == 0
    commands = (
        "encode",
        "render",
        "orbit",
        "mesh",
        "share",
        "info",
        "video",
        "view",
        "demo",
        "train",
        "eval",
        "export",
    )
    for cmd in commands:
        assert cmd in out
        code, out_cmd, _ = run(capsys, cmd, "--help")
        assert code == 0 and out_cmd.startswith(f"usage: lp3d {cmd}"), cmd


def test_train_eval_export_are_the_module_commands() -> None:
    """``lp3d train|eval|export|superres-fit`` take ``python -m lp3d.train|eval|export|superres_fit``'s
    options (one definition)."""
    import argparse

    import lp3d.cli.eval
    import lp3d.cli.export
    import lp3d.cli.superres_fit
    import lp3d.cli.train
    from lp3d.cli import build_parser

    def options(parser: argparse.ArgumentParser) -> list[tuple[object, ...]]:
        return [(a.dest, tuple(a.option_strings), a.default, a.nargs, a.choices) for a in parser._actions]

    for name, module in (
        ("train", lp3d.cli.train),
        ("eval", lp3d.cli.eval),
        ("export", lp3d.cli.export),
        ("superres-fit", lp3d.cli.superres_fit),
    ):
        (sub,) = [a for a in build_parser(name)._actions if isinstance(a, argparse._SubParsersAction)]
        ours, theirs = sub.choices[name], module.build_parser()
        assert len(options(theirs)) > 3 and options(ours) == options(theirs), name
        assert ours.description == theirs.description and ours.prog == f"lp3d {name}"


@pytest.mark.parametrize(
    "module, prog",
    [
        ("lp3d.train", "python -m lp3d.train"),
        ("lp3d.export", "python -m lp3d.export"),
        ("lp3d.superres_fit", "python -m lp3d.superres_fit"),
    ],
)
def test_the_library_commands_run_with_python_m(module: str, prog: str) -> None:
    """The entry points README names for the torch commands (lp3d/train.py or a package's __main__)."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=180
    )
    assert done.returncode == 0 and done.stdout.startswith(f"usage: {prog}"), done.stderr


def test_a_closed_stdout_is_no_error_message(tmp_path) -> None:
    """``lp3d info x.npz | head -1``: when the reader goes away, the command stops quietly with
    status 141 (128 + SIGPIPE, what the shell reports for ``cat`` there); a broken pipe that is not
    stdout's is an error line, and a stdout closed from the start (``>&-``) is one too."""
    import subprocess
    import sys

    script = (
        "import argparse, sys\n"
        "from lp3d.errors import run_command\n"
        "def func(args):\n"
        "    raise BrokenPipeError(32, 'Broken pipe')\n"
        "p = argparse.ArgumentParser(prog='lp3d x')\n"
        "p.set_defaults(func=func)\n"
        "sys.exit(run_command(p, []))\n"
    )
    cmd = [sys.executable, "-c", script]
    reader_gone = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert reader_gone.stdout is not None
    reader_gone.stdout.close()
    _, err = reader_gone.communicate(timeout=60)
    assert reader_gone.returncode == 141 and err == "", err
    other_pipe = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert other_pipe.returncode == 1 and other_pipe.stderr.startswith("lp3d x: error:"), other_pipe
    closed = subprocess.run(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        timeout=60,
        preexec_fn=lambda: __import__("os").close(1),
    )
    assert closed.returncode == 1 and "stdout is closed" in closed.stderr, closed


def test_one_exit_code_policy_for_every_entry_point(capsys, tmp_path) -> None:
    """0 ok, 1 a runtime error (one line, no traceback), 2 a usage error: in ``lp3d`` and in the
    ``python -m lp3d.train|export`` and ``lp3d.cli.eval.main`` alike."""
    from lp3d.cli.eval import main as eval_main
    from lp3d.cli.export import main as export_main
    from lp3d.train import main as train_main

    missing = tmp_path / "missing.pt"
    for argv in (["export", missing, "-o", tmp_path / "y.onnx"], ["eval", missing, "--baseline-steps", "0"]):
        code, _, err = run(capsys, *argv)
        assert code == 1 and "no such file" in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert export_main([str(missing), "-o", str(tmp_path / "y.onnx")]) == 1
    assert eval_main([str(missing)]) == 1
    assert train_main(["--dist-timeout", "-1"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--dist-timeout must be a positive number" in err
    # Usage errors, found by argparse or after it (flags that exclude each other).
    usage = (
        ["export"],  # neither a checkpoint nor --package
        ["export", missing],  # no -o
        ["export", missing, "-o", "x.onnx", "--superres", "a.pt", "--no-superres"],
        ["eval", missing, "--n-identities", "0"],
        ["train", "--config", "no-such-config"],
    )
    for argv in usage:
        code, _, err = run(capsys, *argv)
        assert code == 2 and err.startswith("usage: lp3d ") and f"lp3d {argv[0]}: error:" in err, (argv, err)
    assert export_main([]) == 2 and eval_main(["x.pt", "--n-identities", "0"]) == 2
    assert train_main(["--config", "no-such-config"]) == 2
    assert not list(tmp_path.iterdir())


def test_python_m_lp3d_cli_and_the_import_graph(tmp_path) -> None:
    """``python -m lp3d.cli`` is ``lp3d``; importing the command line loads no torch (train, eval and
    export import it only when named); and no library module imports the command line."""
    import ast
    import subprocess
    import sys

    import lp3d

    code = "import sys, lp3d.cli; assert 'torch' not in sys.modules; sys.exit(lp3d.cli.main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, "info", str(tmp_path / "no.npz")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1 and done.stderr == f"lp3d info: error: {tmp_path / 'no.npz'}: no such file\n"
    done = subprocess.run(
        [sys.executable, "-m", "lp3d.cli", "--version"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.startswith("lp3d "), done.stderr

    root = Path(lp3d.__file__).parent
    offenders = []
    for path in root.rglob("*.py"):
        # A package's __main__.py (python -m lp3d.superres_fit) and lp3d/train.py (python -m lp3d.train)
        # are entry points: they run the command line.
        if root / "cli" in path.parents or path.name == "__main__.py" or path == root / "train.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [f"{node.module}.{a.name}" for a in node.names]
                if isinstance(node, ast.ImportFrom) and node.module
                else []
            )
            if any(n == "lp3d.cli" or n.startswith("lp3d.cli.") for n in names):
                offenders.append(os.path.relpath(path, root))
    assert not offenders, f"library modules importing lp3d.cli: {offenders}"


def test_usage_errors_exit_2(capsys, sphere) -> None:
    assert run(capsys)[0] == 2  # no command
    assert run(capsys, "frobnicate")[0] == 2
    code, _, err = run(capsys, "render", sphere, "-o", "x.png", "--samples", "12+x")
    assert code == 2 and "COARSE+FINE" in err
    assert run(capsys, "render", sphere)[0] == 2  # -o is required
    assert run(capsys, "render", sphere, "-o", "x.png", "--features-channel", "32")[0] == 2
