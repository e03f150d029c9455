"""Running ``lp3d`` in-process for the command-line tests, and their small render settings."""

from __future__ import annotations

from pathlib import Path

import pytest

from lp3d.cli import main

#: Tiny renders: 32² rays, 12+12 samples.
SMALL = ["--resolution", "32", "--samples", "12+12"]
#: The radius of the sample triplane's sphere (``tests/cli/conftest.py``'s ``sphere``).
SPHERE_RADIUS = 0.3


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    """``lp3d ARGV`` in-process: (exit status, stdout, stderr)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def listing(folder: Path) -> set[str]:
    """Every name in ``folder`` (temporary files included: they start with a dot)."""
    return {p.name for p in folder.iterdir()}
