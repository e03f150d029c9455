"""Shared fixtures. GPU tests use the one process-wide lp3d_render device (lavapipe in CI) and
fail loudly, with the adapters seen, when there is none: they are never skipped.

Shared helpers that are not fixtures live in ``tests/support/`` (imported as ``support.*``: this
folder is on ``sys.path`` because it holds this conftest)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def gpu() -> dict[str, str]:
    """The adapter lp3d_render renders on; errors (not skips) when no adapter exists."""
    import lp3d_render

    return lp3d_render.adapter_info()
