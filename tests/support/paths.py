"""Where things are: the repository root and the tests folder, for tests that read the source tree."""

from __future__ import annotations

from pathlib import Path

#: The tests folder (it holds ``conftest.py`` and ``support/``).
TESTS = Path(__file__).resolve().parents[1]
#: The repository root.
REPO = TESTS.parent
