"""The WGSL kernels' named constants equal their Python definitions (one name per quantity,
tied across languages). The kernels cannot import lp3d.render.settings, so this reads them as text: a
renamed, removed or changed constant on either side fails here rather than as a parity drift."""

from __future__ import annotations

import re

import pytest

from lp3d.render import camera, settings
from support.paths import REPO

SHADERS = REPO / "crates" / "renderer" / "shaders"

#: WGSL name -> the Python value it must equal.
PYTHON_VALUES: dict[str, float] = {
    "SIGMOID_MARGIN": settings.SIGMOID_MARGIN,
    "DENSITY_SHIFT": settings.DENSITY_SHIFT,
    "TRANSMITTANCE_EPS": settings.TRANSMITTANCE_EPS,
    "PDF_WEIGHT_FLOOR": settings.PDF_WEIGHT_FLOOR,
    "PDF_EPS": settings.PDF_EPS,
    "MAX_SAMPLES": settings.MAX_SAMPLES,
    "N_CHANNELS": settings.N_CHANNELS,
    "HIDDEN": settings.HIDDEN,
    "CAMERA_FLOATS": camera.LABEL_SIZE,
}

# `const NAME[: type] = literal;` at the start of a line; literals as WGSL writes them (1.0, 1e-10,
# 256u, 0.001).
CONST = re.compile(r"^const\s+([A-Z_][A-Z0-9_]*)\s*(?::\s*\w+)?\s*=\s*([0-9.eE+-]+)[uif]?\s*;", re.M)


def wgsl_constants() -> dict[str, tuple[float, str]]:
    """Every top-level numeric ``const`` in the shaders: name -> (value, file)."""
    found: dict[str, tuple[float, str]] = {}
    for path in sorted(SHADERS.glob("*.wgsl")):
        for name, literal in CONST.findall(path.read_text()):
            assert name not in found, f"{name} is defined in both {found[name][1]} and {path.name}"
            found[name] = (float(literal), path.name)
    return found


def test_the_parser_reads_the_shaders() -> None:
    found = wgsl_constants()
    assert len(found) >= len(PYTHON_VALUES), sorted(found)


@pytest.mark.parametrize("name", sorted(PYTHON_VALUES))
def test_wgsl_constant_equals_python(name: str) -> None:
    found = wgsl_constants()
    assert name in found, (
        f"no `const {name}` in {SHADERS} (renamed? update this test and lp3d.render.settings)"
    )
    value, where = found[name]
    assert value == PYTHON_VALUES[name], f"{where}: {name} = {value}, Python has {PYTHON_VALUES[name]}"
