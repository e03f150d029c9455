"""The hand-written stubs match the native module's runtime signatures, and the installed package
ships what users import (native module, stubs, py.typed, the lp3d package)."""

from __future__ import annotations

import ast
import importlib.metadata
import inspect
from pathlib import Path

import lp3d_render
from lp3d_render import _lp3d_render

STUB = Path(lp3d_render.__file__).with_name("_lp3d_render.pyi")


def stub_signatures() -> dict[str, list[tuple[str, str | None, str]]]:
    """name -> [(param, default source or None, kind)] for stub functions and Triplane.__init__."""
    tree = ast.parse(STUB.read_text())
    out = {}

    def params(fn: ast.FunctionDef) -> list[tuple[str, str | None, str]]:
        a = fn.args
        pos = a.posonlyargs + a.args
        defaults = [None] * (len(pos) - len(a.defaults)) + [ast.unparse(d) for d in a.defaults]
        res = [(p.arg, d, "positional") for p, d in zip(pos, defaults, strict=True) if p.arg != "self"]
        res += [
            (p.arg, None if d is None else ast.unparse(d), "keyword_only")
            for p, d in zip(a.kwonlyargs, a.kw_defaults, strict=True)
        ]
        return res

    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            out[node.name] = params(node)
        if isinstance(node, ast.ClassDef) and node.name == "Triplane":
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name in (
                    "__init__",
                    "load",
                    "save",
                    "bake_occupancy",
                ):
                    out[f"Triplane.{item.name}"] = params(item)
    return out


def runtime_params(obj) -> list[tuple[str, str | None, str]]:
    sig = inspect.signature(obj)
    res = []
    for p in sig.parameters.values():
        if p.name in ("self", "cls"):
            continue
        default = None if p.default is inspect.Parameter.empty else repr(p.default)
        kind = "keyword_only" if p.kind is inspect.Parameter.KEYWORD_ONLY else "positional"
        res.append((p.name, default, kind))
    return res


def test_stub_signatures_match_runtime() -> None:
    stubs = stub_signatures()
    runtime = {
        "render": _lp3d_render.render,
        "adapter_info": _lp3d_render.adapter_info,
        "last_frame_device_bytes": _lp3d_render.last_frame_device_bytes,
        "Triplane.bake_occupancy": _lp3d_render.Triplane.bake_occupancy,
        "look_at_camera": _lp3d_render.look_at_camera,
        "shader_sources": _lp3d_render.shader_sources,
        "Triplane.__init__": _lp3d_render.Triplane,
        "Triplane.load": _lp3d_render.Triplane.load,
        "Triplane.save": _lp3d_render.Triplane.save,
        "view": _lp3d_render.view,
        "view_options": _lp3d_render.view_options,
        "bake": _lp3d_render.bake,
        "attach_baked": _lp3d_render.attach_baked,
    }
    assert set(stubs) == set(runtime)
    for name, obj in runtime.items():
        got = [(n, None if d is None else repr(ast.literal_eval(d)), k) for n, d, k in stubs[name]]
        want = [(n, None if d is None else repr(ast.literal_eval(d)), k) for n, d, k in runtime_params(obj)]
        assert got == want, name


def test_public_names_are_stubbed() -> None:
    tree = ast.parse(STUB.read_text())
    stubbed = {n.name for n in tree.body if isinstance(n, ast.FunctionDef | ast.ClassDef)}
    stubbed |= {t.target.id for t in tree.body if isinstance(t, ast.AnnAssign)}
    assert set(lp3d_render.__all__) <= stubbed
    for name in lp3d_render.__all__:
        assert hasattr(_lp3d_render, name), name


def test_installed_files() -> None:
    files = {str(f) for f in importlib.metadata.files("lp3d") or []}
    for expected in (
        "lp3d_render/__init__.py",
        "lp3d_render/_lp3d_render.pyi",
        "lp3d_render/py.typed",
        "lp3d/__init__.py",
        "lp3d/render/reference.py",
        "lp3d/render/camera.py",
        "lp3d/share/page.html",  # lp3d share's data files
        "lp3d/share/gpu.js",
        "lp3d/share/viewer.js",
    ):
        assert expected in files, expected
    assert any(f.startswith("lp3d_render/_lp3d_render") and f.endswith(".so") for f in files)
