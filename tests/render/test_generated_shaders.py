"""crates/renderer/shaders/decoder.wgsl is generated (fully unrolled MLP); it must match its generator."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from support.paths import REPO

ROOT = REPO
DECODER = Path("crates/renderer/shaders/decoder.wgsl")


def test_decoder_wgsl_is_current() -> None:
    generated = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gen_decoder_wgsl.py")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    committed = (ROOT / DECODER).read_text()
    assert generated == committed, f"run: python scripts/gen_decoder_wgsl.py > {DECODER}"
