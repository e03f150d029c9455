"""The maps a newcomer reads match the code: docs/architecture.md names every Python module in its
subpackage's row and every Rust source file, and the renderer crate's own module list
(``crates/renderer/src/lib.rs``) names every module it declares. A new module fails here until the
map says where it sits."""

from __future__ import annotations

import re

from support.paths import REPO

ARCHITECTURE = (REPO / "docs" / "architecture.md").read_text()
PACKAGE = REPO / "python" / "lp3d"


def subpackage_row(subpackage: str) -> str:
    """The text of architecture.md's layer table rows for ``subpackage/`` (e.g. ``render/``)."""
    rows = [line for line in ARCHITECTURE.splitlines() if line.startswith("|") and f"`{subpackage}/`" in line]
    assert rows, f"docs/architecture.md has no layer-table row for `{subpackage}/`"
    return "\n".join(rows)


def test_architecture_names_every_python_module_in_its_row() -> None:
    missing = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name in ("__init__.py", "__main__.py"):
            continue
        relative = path.relative_to(PACKAGE)
        if len(relative.parts) == 1:
            where = ARCHITECTURE  # layer 0's modules share one row
        else:
            where = subpackage_row(relative.parts[0])
        if f"`{relative.name}`" not in where and f"{relative.name}`" not in where:
            missing.append(str(relative))
    assert not missing, f"modules docs/architecture.md does not place: {missing}"


def test_architecture_names_every_rust_source_file() -> None:
    missing = []
    for path in sorted((REPO / "crates").glob("*/src/**/*.rs")):
        if path.name in ("lib.rs", "main.rs"):
            continue
        src = REPO / "crates" / path.relative_to(REPO / "crates").parts[0] / "src"
        if path.name not in ARCHITECTURE and str(path.relative_to(src)) not in ARCHITECTURE:
            missing.append(str(path.relative_to(REPO)))
    assert not missing, f"Rust files docs/architecture.md does not place: {missing}"


def test_the_renderer_crate_lists_its_modules() -> None:
    lib = (REPO / "crates" / "renderer" / "src" / "lib.rs").read_text()
    declared = re.findall(r"^pub mod (\w+);", lib, flags=re.MULTILINE)
    docs = "\n".join(line for line in lib.splitlines() if line.startswith("//!"))
    missing = [name for name in declared if f"[`{name}`]" not in docs]
    assert declared and not missing, f"crates/renderer/src/lib.rs declares but does not describe: {missing}"


def test_the_map_check_catches_a_missing_module() -> None:
    """The row lookup is what the Python check relies on: a name absent from a row is absent."""
    assert "`camera.py`" in subpackage_row("render")
    assert "`no_such_module.py`" not in subpackage_row("render")
