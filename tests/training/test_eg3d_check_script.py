"""``scripts/eg3d_check.py`` without EG3D: its argument checks, its table file and its failure path.

The check itself needs NVlabs/eg3d's source, which CI does not have; these tests keep the script from
rotting silently: every usage error is a clear exit 2, a step that fails is reported in the table with
the steps that need it skipped (exit 1), and the table section is written without touching the rest of
its file.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from support.paths import REPO

SCRIPT = REPO / "scripts" / "eg3d_check.py"


@pytest.fixture(scope="module")
def script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("eg3d_check", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["eg3d_check"] = module  # dataclasses look their module up while being built
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules["eg3d_check"]
    return module


def fake_eg3d_tree(root: Path, files: tuple[str, ...], *, text: str = "") -> Path:
    """A folder with EG3D's file names, each holding ``text``."""
    for rel in files:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root


def usage_error(script: ModuleType, argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as e:
        script.main(argv)
    assert e.value.code == 2
    return capsys.readouterr().err


def test_help_names_the_options() -> None:
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--help"], capture_output=True, text=True, check=True, timeout=60
    ).stdout
    for flag in ("--eg3d-source", "--work", "--device", "--resolution", "--seed", "--table"):
        assert flag in out
    assert "--worker" not in out  # internal


def test_usage_errors_name_the_bad_option(
    script: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert "--eg3d-source is required" in usage_error(script, [], capsys)
    err = usage_error(script, ["--eg3d-source", str(tmp_path / "nope")], capsys)
    assert "--eg3d-source" in err and "no such directory" in err

    # A tree with EG3D's packages but not its files (as the adapter tests' fake) is named as such.
    partial = fake_eg3d_tree(tmp_path / "partial", ("torch_utils/__init__.py", "dnnlib/__init__.py"))
    err = usage_error(script, ["--eg3d-source", str(partial)], capsys)
    assert "not NVlabs/eg3d's eg3d/ folder" in err
    assert "training/triplane.py" in err and "legacy.py" in err and "dnnlib/__init__.py" not in err

    src = fake_eg3d_tree(tmp_path / "repo" / "eg3d", script.EG3D_FILES)
    base = ["--eg3d-source", str(tmp_path / "repo")]  # the repository root is accepted
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x").write_text("")
    (tmp_path / "doc.md").write_text(f"# t\n{script.SECTION_BEGIN}\nold\n")  # no end marker
    for extra, needle in [
        (["--resolution", "0"], "--resolution must be in [1, 512]"),
        (["--resolution", "513"], "--resolution must be in [1, 512]"),
        (["--seed", "-1"], "--seed must be in [0, 2**32)"),
        (["--device", "tpu"], "--device must be cpu, cuda or cuda:N"),
        (["--step-timeout", "0"], "--step-timeout must be > 0"),
        (["--work", str(tmp_path / "busy")], "must be a new or empty folder"),
        (["--table", str(tmp_path)], "is not a file"),
        (["--table", str(tmp_path / "doc.md")], "only one of the markers"),
    ]:
        assert needle in usage_error(script, base + extra, capsys), extra
    assert script.resolve_eg3d_source(str(tmp_path / "repo")) == src.resolve()


def test_table_section_replaces_only_its_part(script: ModuleType) -> None:
    begin, end = script.SECTION_BEGIN, script.SECTION_END
    fresh = script.replace_section("", "| a |\n")
    assert fresh.startswith("# EG3D check\n") and f"{begin}\n| a |\n{end}\n" in fresh
    doc = f"# Title\n\nintro\n\n{begin}\nold table\n{end}\n\nafter\n"
    new = script.replace_section(doc, "new table\n")
    assert new == f"# Title\n\nintro\n\n{begin}\nnew table\n{end}\nafter\n"
    assert script.replace_section(new, "new table\n") == new  # idempotent
    appended = script.replace_section("# Other\n", "t\n")
    assert appended == f"# Other\n\n{begin}\nt\n{end}\n"


def test_lp3d_steps_run_without_eg3d_on_their_path(script: ModuleType, tmp_path: Path) -> None:
    src = fake_eg3d_tree(tmp_path / "eg3d", ("training/__init__.py", "dnnlib/__init__.py"))
    check = script.Check(
        script=SCRIPT,
        eg3d_source=src.resolve(),
        work=tmp_path,
        device="cpu",
        seed=0,
        resolution=8,
        step_timeout=10.0,
    )
    other = str(tmp_path / "other")
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(src), other])
    try:
        assert check.env(eg3d=False)["PYTHONPATH"] == other
        assert check.env(eg3d=True)["PYTHONPATH"] == os.pathsep.join([str(src.resolve()), other])
    finally:
        if old is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = old
    # The lp3d-side worker's own guard sees EG3D's packages when they are importable from the source.
    assert script._eg3d_importable_from(src.resolve()) == []
    sys.path.insert(0, str(src))
    importlib.invalidate_caches()
    try:
        assert script._eg3d_importable_from(src.resolve()) == ["dnnlib", "training"]
    finally:
        sys.path.remove(str(src))
        importlib.invalidate_caches()


def test_a_failing_step_is_reported_and_what_needs_it_is_skipped(script: ModuleType, tmp_path: Path) -> None:
    """End to end with a source tree whose ``dnnlib`` cannot be imported: the EG3D build step fails
    with its error in the table, every later step is skipped, the exit status is 1, and the table goes
    into its section of the given file."""
    src = fake_eg3d_tree(tmp_path / "eg3d", script.EG3D_FILES)
    (src / "dnnlib" / "__init__.py").write_text("raise ImportError('stand-in tree: not EG3D')\n")
    doc = tmp_path / "doc.md"
    doc.write_text(f"# Kept\n\n{script.SECTION_BEGIN}\nold\n{script.SECTION_END}\n\ntail\n")
    work = tmp_path / "work"
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--eg3d-source", str(src), "--work", str(work), "--table", str(doc)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    out = proc.stdout
    n = len(script.STEPS)
    assert f"[1/{n}] build:" in out and f"[{n}/{n}] " in out
    assert "| build | **FAIL** | exit status 1: " in out and "stand-in tree: not EG3D" in out
    for step in script.STEPS[1:]:
        assert f"| {step.name} | skipped | skipped: needs " in out, step.name
    assert "Verdict: FAILED." in out
    assert (work / "logs" / "eg3d-build.log").is_file()
    text = doc.read_text()
    assert text.startswith("# Kept\n\n") and text.endswith("\ntail\n") and "\nold\n" not in text
    assert "| build | **FAIL** |" in text and "Command: `python scripts/eg3d_check.py" in text
