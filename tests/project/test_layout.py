"""The package's layout (docs/architecture.md): subpackages import only the layers below them, no
module imports itself back through a cycle or imports another module's private names, and no module
answers to an old path or re-exports another's names for old imports (CHANGELOG.md lists what went)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import sys
from pathlib import Path

import pytest

import lp3d
from support.paths import REPO

ROOT = Path(lp3d.__file__).parent

#: What each part of the package may import from lp3d (function-local imports included). Plumbing
#: (errors, atomic, array_cache, images, outputs) sits at the bottom; the command line at the top.
ALLOWED = {
    "errors": set(),
    "atomic": set(),
    "array_cache": {"atomic"},
    "images": {"atomic"},
    "outputs": {"atomic", "errors"},
    "render": {"atomic", "errors"},
    "photo": {"errors", "render"},
    "nets": set(),
    "teachers": {"render", "nets", "images", "atomic", "errors"},
    "lift": {"render", "nets", "array_cache", "atomic", "errors"},
    "share": {"render", "atomic", "errors", "__version__"},
    # lp3d serve's web app: photos and webcam frames lifted (photo, lift), drawn by share's page scripts;
    # images and outputs for the orbit GIF download.
    "serve": {"share", "lift", "photo", "render", "images", "outputs", "atomic", "errors", "__version__"},
    # outputs: lp3d export's check that no output replaces an input (lp3d.outputs.check_distinct).
    "training": {
        "render",
        "nets",
        "lift",
        "teachers",
        "photo",
        "array_cache",
        "atomic",
        "errors",
        "images",
        "outputs",
    },
    # Beside training, each its own job: they use the trained student, never the reverse.
    "evaluation": {"training", "render", "nets", "lift", "teachers", "photo", "atomic", "errors", "images"},
    "superres_fit": {
        "training",
        "render",
        "nets",
        "lift",
        "teachers",
        "array_cache",
        "atomic",
        "errors",
        "images",
    },
    "export": {"training", "superres_fit", "render", "nets", "lift", "atomic", "errors", "outputs"},
    # python -m lp3d.train, the README's command: an entry point that runs lp3d.cli.train, nothing else.
    "train": {"cli"},
    # The library commands (train, eval, export, superres-fit) are imported inside the functions that
    # parse or run them, so that lp3d encode never imports torch.
    "cli": {
        "training",
        "evaluation",
        "export",
        "superres_fit",
        "render",
        "photo",
        "lift",
        "teachers",
        "share",
        "serve",
        "errors",
        "images",
        "outputs",
        "atomic",
        "__version__",
    },
    "__init__": set(),
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in ROOT.rglob("*.py")}


def lp3d_imports(path: Path, top_level_only: bool = False) -> set[str]:
    """The lp3d modules (and ``lp3d.X`` names) that ``path`` imports, absolute imports only."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else ast.walk(tree)
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            assert node.level == 0, f"{path}: relative import (lp3d uses absolute imports)"
            found |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    return {m for m in found if m == "lp3d" or m.startswith("lp3d.")}


def part_of(name: str) -> str:
    """``lp3d.render.camera`` -> ``render``; the top-level ``lp3d`` package itself -> ``__init__``."""
    return name.split(".")[1] if "." in name else "__init__"


def test_every_part_has_a_rule() -> None:
    assert {part_of(m) for m in MODULES} <= set(ALLOWED)


def layer_violations(modules: dict[str, Path]) -> list[str]:
    """``"A imports B"`` for every import of a part that :data:`ALLOWED` does not list for A's part."""
    found = []
    for name, path in modules.items():
        # A package's __main__ is an entry point (python -m lp3d.export): it runs the command line.
        part = "cli" if name.endswith(".__main__") else part_of(name)
        for target in sorted(lp3d_imports(path)):
            other = part_of(target)
            if other not in (part, "__init__") and other not in ALLOWED[part]:
                found.append(f"{name} imports {target}")
    return found


def test_each_part_imports_only_the_layers_below_it() -> None:
    assert layer_violations(MODULES) == []


def test_the_layer_check_catches_an_upward_import(tmp_path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from lp3d.cli.common import say\n")
    assert layer_violations({"lp3d.render.probe": probe}) == [
        "lp3d.render.probe imports lp3d.cli.common",
        "lp3d.render.probe imports lp3d.cli.common.say",
    ]


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


@pytest.mark.parametrize("top_level_only", [True, False], ids=["module-level", "with-lazy-imports"])
def test_no_import_cycle(top_level_only: bool) -> None:
    graph = {
        name: {m for m in lp3d_imports(path, top_level_only) if m in MODULES} - {name}
        for name, path in MODULES.items()
    }
    assert _cycles(graph) == []


#: Some old module paths, once aliases of moved modules (CHANGELOG.md lists them all): a module is
#: imported by its own path only.
REMOVED_PATHS = ("lp3d._moved", "lp3d.camera", "lp3d.render_torch", "lp3d.eval", "lp3d.training.cli")
#: What each entry point exports: its command, not other modules' names.
ENTRY_POINT_NAMES = {
    "lp3d.train": {"main"},
    "lp3d.cli": {"COMMANDS", "build_parser", "main", "standalone_parser"},
}


def test_no_alias_of_an_old_path_or_name() -> None:
    """No import hook of lp3d's on ``sys.meta_path``, no module at an old path, and the entry points
    ``lp3d.train`` (``python -m lp3d.train``) and ``lp3d.cli`` (``lp3d``) export only their own names."""
    assert not [f for f in sys.meta_path if type(f).__module__.startswith("lp3d")]
    for old in REMOVED_PATHS:
        assert importlib.util.find_spec(old) is None, old
    for name, own in ENTRY_POINT_NAMES.items():
        assert set(importlib.import_module(name).__all__) == own, name
    train = importlib.import_module("lp3d.train")
    assert {n for n in vars(train) if not n.startswith("_")} == {"annotations", "main"}


def private_imports(modules: dict[str, Path]) -> list[str]:
    """``"A imports B._name"`` for every ``from B import _name`` of another lp3d module's private name,
    and every ``B._name`` read through a module ``B`` that A imported (``from lp3d.x import b``,
    ``import lp3d.x.b as b``, ``lp3d.x.b._name``)."""
    found = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        imported: dict[str, str] = {}  # local name -> the lp3d module it is
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                imported |= {a.asname: a.name for a in node.names if a.asname and a.name in MODULES}
            elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lp3d"):
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    if full in MODULES:
                        imported[alias.asname or alias.name] = full
                    # A package's own private submodule (lp3d.cli._startup) is its own.
                    own = (
                        full in MODULES
                        and node.module == name.rpartition(".")[0]
                        or (node.module == name and f"{name}.{alias.name}" in MODULES)
                    )
                    if _private(alias.name) and not own:
                        found.append(f"{name} imports {full}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _private(node.attr):
                of = _dotted(node.value)
                other = imported.get(of, of if of in MODULES else None)
                own = other == name or (
                    f"{other}.{node.attr}" in MODULES and other == name.rpartition(".")[0]
                )
                if other is not None and not own:
                    found.append(f"{name} imports {other}.{node.attr}")
    return found


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_module_imports_another_modules_private_names() -> None:
    """No module of lp3d reads another's private names: a shared name is public API of its
    module. (Tests may: they check a module from inside.)"""
    assert private_imports(MODULES) == []


def test_the_private_import_check_catches_one(tmp_path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("from lp3d.evaluation.protocol import _secret\n")
    assert private_imports({"lp3d.export.probe": probe}) == [
        "lp3d.export.probe imports lp3d.evaluation.protocol._secret"
    ]
    probe.write_text(
        "import lp3d.lift.sidecar as side\nfrom lp3d.lift import model_package\nimport lp3d.render.camera\n"
        "side._a, model_package._b, lp3d.render.camera._c, model_package.__name__, side.public\n"
    )
    assert private_imports({"lp3d.lift.probe": probe}) == [
        "lp3d.lift.probe imports lp3d.lift.sidecar._a",
        "lp3d.lift.probe imports lp3d.lift.model_package._b",
        "lp3d.lift.probe imports lp3d.render.camera._c",
    ]


#: One concept, one definition: the module each lives in. Elsewhere a module imports it;
#: :func:`definitions` says what would be a second one.
ONE_HOME = {
    "PSNR": "lp3d.render.psnr",
    "cosine schedule": "lp3d.nets.lr_schedule",
    "latest checkpoint": "lp3d.lift.run_checkpoints",
    "atomic write": "lp3d.atomic",
    "timer": "lp3d.evaluation.protocol",
}

#: Second definitions left for a change of their own, each with the reason (the test fails once one
#: is gone, so that the entry goes too).
LEFT_ELSEWHERE = {
    ("cosine schedule", "lp3d.lift.pose"): "fit_pose's camera-step decay to 0 computes "
    "cos(pi * i / n), not cos(pi * (i / n)): moving it to cosine_decay changes refine's learning "
    "rates in the last bit, so it is left to a change of lp3d.lift.pose that says so",
}


def _dotted(node: ast.AST) -> str:
    """``torch.log10`` for the callee ``torch.log10``; ``""`` for one that is not a plain name."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value)
        return f"{inner}.{node.attr}" if inner else node.attr
    return ""


def _times_pi(node: ast.AST) -> bool:
    """Whether ``node`` holds a product with ``pi`` (``math.pi * t``, ``np.pi * i / n``)."""
    return any(
        isinstance(n, ast.BinOp)
        and isinstance(n.op, ast.Mult)
        and any(_dotted(side).rsplit(".", 1)[-1] == "pi" for side in (n.left, n.right))
        for n in ast.walk(node)
    )


def _decibel_logs(tree: ast.AST) -> set[int]:
    """The ids of the ``log10`` calls that make decibels: a factor of 10 or 20 times them (a PSNR is
    ``10 * log10(peak / mse)``; a plot's log axis is a bare ``log10``)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult):
            for factor, other in ((node.left, node.right), (node.right, node.left)):
                if isinstance(factor, ast.UnaryOp) and isinstance(factor.op, ast.USub):
                    factor = factor.operand  # -10 * log10(mse)
                if isinstance(factor, ast.Constant) and factor.value in (10, 20):
                    if isinstance(other, ast.Call) and _dotted(other.func).rsplit(".", 1)[-1] == "log10":
                        found.add(id(other))
    return found


def definitions(path: Path) -> set[str]:
    """The :data:`ONE_HOME` concepts that ``path`` defines: a function named like one (``psnr``,
    ``*cosine*``, ``latest_*checkpoint*``/``newest_readable``, ``*atomic*``) or the computation itself
    (``10 * log10``: a PSNR; ``cos(pi * t)``: a cosine schedule; a ``glob``/``re.compile`` of
    ``step-*`` names: the checkpoint rule; ``fsync``/``mkstemp``/``NamedTemporaryFile``: an atomic
    writer)."""
    found: set[str] = set()
    tree = ast.parse(path.read_text())
    decibels = _decibel_logs(tree)
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            name = node.name.lower()
            if name.strip("_") in ("psnr", "psnr_db"):
                found.add("PSNR")
            if "cosine" in name:
                found.add("cosine schedule")
            if ("latest" in name or "newest" in name) and ("checkpoint" in name or "readable" in name):
                found.add("latest checkpoint")
            if "atomic" in name:
                found.add("atomic write")
            if name.strip("_") in ("timed", "timer", "timeit", "median_ms"):
                found.add("timer")
        elif isinstance(node, ast.Call):
            callee = _dotted(node.func)
            last = callee.rsplit(".", 1)[-1]
            args = [*node.args, *(k.value for k in node.keywords)]
            if last == "log10" and id(node) in decibels:
                found.add("PSNR")
            if last == "cos" and any(_times_pi(a) for a in args):
                found.add("cosine schedule")
            steps = any(
                isinstance(c, ast.Constant) and isinstance(c.value, str) and "step-" in c.value
                for a in args
                for c in ast.walk(a)
            )
            if steps and (last in ("glob", "rglob", "iglob") or callee == "re.compile"):
                found.add("latest checkpoint")
            if last in ("fsync", "mkstemp", "NamedTemporaryFile"):
                found.add("atomic write")
    return found


def test_each_concept_has_one_definition() -> None:
    """PSNR, the cosine schedule, the latest readable checkpoint, the atomic writer and the timer are
    each defined in their :data:`ONE_HOME` module only (while there were several, heldout.csv and
    report.json, ``lp3d encode --model RUN`` and ``lp3d eval RUN`` could disagree)."""
    homes = {home: concept for concept, home in ONE_HOME.items()}
    for concept, home in ONE_HOME.items():
        assert concept in definitions(MODULES[home]), f"{home} no longer defines the {concept}"
    found = {
        (concept, name)
        for name, path in MODULES.items()
        for concept in definitions(path)
        if homes.get(name) != concept
    }
    unexplained = sorted(found - LEFT_ELSEWHERE.keys())
    assert not unexplained, (
        "a second definition (use the one in its home, "
        + ", ".join(f"{c}: {h}" for c, h in ONE_HOME.items())
        + f"): {unexplained}"
    )
    assert not LEFT_ELSEWHERE.keys() - found, "a second definition left elsewhere is gone: drop its entry"


#: The benchmarks' and scripts' home of what they share. Their timer is their own (lp3d's,
#: :func:`lp3d.evaluation.protocol.timed`, synchronises a torch device and would import training
#: into every benchmark); every other concept comes from lp3d (``lp3d.render.psnr`` above all: four
#: PSNRs once disagreed in bench/).
BENCH_HARNESS = REPO / "bench" / "harness.py"


def test_bench_and_scripts_define_no_concept_of_their_own() -> None:
    """bench/ and scripts/ import PSNR, schedules, checkpoints and atomic writes from lp3d, and their
    one timer from ``bench/harness.py``."""
    assert definitions(BENCH_HARNESS) == {"timer"}, "bench/harness.py no longer defines the timer"
    found = sorted(
        f"{path.relative_to(REPO)}: {concept}"
        for folder in ("bench", "scripts")
        for path in sorted((REPO / folder).glob("*.py"))
        if path != BENCH_HARNESS
        for concept in definitions(path)
    )
    assert not found, f"a second definition in bench/ or scripts/ (import lp3d's, or the harness's): {found}"


def test_the_one_definition_check_catches_a_second(tmp_path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import math, torch\n"
        "def score(a, b):\n    return 10 * torch.log10(4 / (a - b).square().mean())\n"
        "def score2(mse):\n    return -10.0 * math.log10(mse)\n"
        "def lr(step, total):\n    return 0.5 * (1 + math.cos(math.pi * step / total))\n"
        "def last(run):\n    return sorted(run.glob('checkpoints/step-*.pt'))[-1]\n"
        "def _atomic_save(obj, path):\n    pass\n"
        "def timed(fn, n):\n    return fn()\n"
    )
    assert definitions(probe) == set(ONE_HOME)
    probe.write_text("import math\ndef score(mse):\n    return -10.0 * math.log10(mse)\n")
    assert definitions(probe) == {"PSNR"}
    probe.write_text("from lp3d.render.psnr import psnr\ndef score(a, b):\n    return psnr(a, b).mean()\n")
    assert definitions(probe) == set()
    probe.write_text("import math\ndef axis(ms, lo, hi):\n    return (math.log10(ms) - lo) / (hi - lo)\n")
    assert definitions(probe) == set(), "a plot's log axis is no PSNR"


#: Longest module, and longest function body (docstring excluded), that need no written reason.
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80


def test_modules_stay_small() -> None:
    long = {
        name: n
        for name, path in MODULES.items()
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def _function_lengths(path: Path) -> list[tuple[str, int, bool]]:
    """``(name, lines without the docstring, a '# Long because:' comment above it)`` per function."""
    lines = path.read_text().splitlines()
    found = []
    for node in ast.walk(ast.parse("\n".join(lines))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            first = node.body[0]
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                length -= first.end_lineno - first.lineno + 1
            top = min([d.lineno for d in node.decorator_list] + [node.lineno])
            reason = any("# Long because:" in lines[i] for i in range(max(0, top - 4), top - 1))
            found.append((node.name, length, reason))
    return found


def test_long_functions_say_why() -> None:
    unexplained = [
        f"{name}.{fn} ({n} lines)"
        for name, path in MODULES.items()
        for fn, n, reason in _function_lengths(path)
        if n > MAX_FUNCTION_LINES and not reason
    ]
    assert not unexplained, (
        f"functions over {MAX_FUNCTION_LINES} lines without '# Long because:': {unexplained}"
    )


#: The Rust crates' sources: the same function rule (a reason is a ``// Long because:`` comment).
RUST_SOURCES = sorted((REPO / "crates").glob("*/src/**/*.rs"))
_RUST_FN = re.compile(r"^(\s*)(?:pub(?:\([a-z]+\))? )?(?:const )?(?:async )?(?:unsafe )?fn (\w+)")


def _rust_function_lengths(path: Path) -> list[tuple[str, int, bool]]:
    """``(name, lines from ``fn`` to its closing brace, a '// Long because:' comment in the four
    lines above)`` per function; rustfmt's layout makes the closing brace the first line after
    ``fn`` at the same indent that is a lone ``}``."""
    lines = path.read_text().splitlines()
    found = []
    for i, line in enumerate(lines):
        m = _RUST_FN.match(line)
        if m is None or line.rstrip().endswith(";"):
            continue
        end = next((j for j in range(i + 1, len(lines)) if lines[j] == m.group(1) + "}"), None)
        if end is None:
            continue
        reason = any("// Long because:" in lines[k] for k in range(max(0, i - 4), i))
        found.append((m.group(2), end - i + 1, reason))
    return found


def test_rust_modules_stay_small() -> None:
    """The same 500-line rule for the crates' modules, counting the code before its inline
    ``#[cfg(test)]`` tests."""
    long = {}
    for path in RUST_SOURCES:
        lines = path.read_text().splitlines()
        code = next((i for i, line in enumerate(lines) if line.startswith("#[cfg(test)]")), len(lines))
        if code > MAX_MODULE_LINES:
            long[str(path.relative_to(REPO))] = code
    assert not long, f"Rust modules over {MAX_MODULE_LINES} lines of code: {long}"


def _rust_module_imports() -> dict[str, dict[str, set[str]]]:
    """Per crate: each top-level module (a child module counts as its parent) -> the modules of the
    same crate it names through ``crate::``. ``lib.rs`` and ``main.rs`` only declare and re-export."""
    crates: dict[str, dict[str, set[str]]] = {}
    for path in RUST_SOURCES:
        src = next(p for p in path.parents if p.name == "src")
        rel = path.relative_to(src)
        if rel.as_posix() in ("lib.rs", "main.rs"):
            continue
        module = rel.parts[0].removesuffix(".rs")
        code = re.sub(r"//.*", "", path.read_text())  # paths in comments name, they do not import
        named = set(re.findall(r"\bcrate::(\w+)", code)) - {module}
        crates.setdefault(src.parent.name, {}).setdefault(module, set()).update(named)
    return crates


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every cycle a depth-first walk of ``graph`` meets, as the modules along it."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    found: list[list[str]] = []

    def visit(trail: list[str]) -> None:
        state[trail[-1]] = 1
        for nxt in sorted(graph.get(trail[-1], ())):
            if state.get(nxt) == 1:
                found.append(trail[trail.index(nxt) :] + [nxt])
            elif nxt in graph and nxt not in state:
                visit(trail + [nxt])
        state[trail[-1]] = 2

    for module in sorted(graph):
        if module not in state:
            visit([module])
    return found


def test_rust_modules_import_without_cycles() -> None:
    """Inside each crate, modules form layers too: no module reaches itself through ``crate::``
    paths (Rust would allow it; a newcomer reading bottom-up could not)."""
    cycles = [
        f"{crate}: {' -> '.join(cycle)}"
        for crate, graph in _rust_module_imports().items()
        for cycle in _cycles(graph)
    ]
    assert not cycles, f"Rust module cycles: {cycles}"
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c", "a"]]


def test_long_rust_functions_say_why() -> None:
    assert RUST_SOURCES, "no Rust sources found beside the package"
    unexplained = [
        f"{path.relative_to(REPO)}:{fn} ({n} lines)"
        for path in RUST_SOURCES
        for fn, n, reason in _rust_function_lengths(path)
        if n > MAX_FUNCTION_LINES and not reason
    ]
    assert not unexplained, (
        f"Rust functions over {MAX_FUNCTION_LINES} lines without '// Long because:': {unexplained}"
    )


def test_the_rust_length_check_reads_reasons(tmp_path) -> None:
    body = "".join(f"    let x{i} = {i};\n" for i in range(MAX_FUNCTION_LINES))
    plain, explained = tmp_path / "a.rs", tmp_path / "b.rs"
    plain.write_text(f"/// Doc.\npub fn f() {{\n{body}}}\n")
    explained.write_text(f"// Long because: one table.\nfn f() {{\n{body}}}\n")
    assert _rust_function_lengths(plain) == [("f", MAX_FUNCTION_LINES + 2, False)]
    assert _rust_function_lengths(explained) == [("f", MAX_FUNCTION_LINES + 2, True)]


def test_the_length_check_reads_reasons(tmp_path) -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES + 1))
    plain, explained = tmp_path / "a.py", tmp_path / "b.py"
    plain.write_text(f'def f():\n    """Doc."""\n{body}')
    explained.write_text(f"# Long because: one table, read top to bottom.\ndef f():\n{body}")
    assert _function_lengths(plain) == [("f", MAX_FUNCTION_LINES + 2, False)]  # def line + body
    assert _function_lengths(explained) == [("f", MAX_FUNCTION_LINES + 2, True)]
