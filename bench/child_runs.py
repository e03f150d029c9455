"""What the A/B bench scripts (`drag_frames.py`, `full_walk.py`) share: each runs its own timing in
fresh child processes that differ only in their environment (a build on ``PYTHONPATH``, a setting
like ``LP3D_FULL_WALK``), alternated so that a slow spell of the machine hits every side, and
writes a Markdown table."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def child_rows(script: str, child_args: list[str], env: dict[str, str]) -> list[dict]:
    """Runs ``script --child child_args`` under ``env``; the JSON objects it printed, one per line."""
    cmd = [sys.executable, script, "--child", *child_args]
    done = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True, check=True)
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def emit_table(lines: list[str], out: Path | None) -> None:
    """Prints the table and, with ``out``, writes it there too."""
    table = "\n".join(lines)
    print("\n" + table)
    if out:
        out.write_text(table + "\n")
