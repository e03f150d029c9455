"""A fuzzer over model packages: mutated sidecars, ONNX files and torch weights files go
through the public loader (:func:`lp3d.lift.inference.load_encoder`, or ``load_model_package`` for a
``.json``) and, when they load, encode one image and make its triplane (and run the super-resolution
network when there is one). Every case must end in success or a
:class:`~lp3d.lift.model_package.ModelPackageError` (a ValueError) that names the file in under 2,000
characters - never another exception, a hang or a crash. Each case runs under a deadline.

The seeds are a valid package made here: a ``micro`` encoder (the real architecture with ~20k
parameters, 32² in, 8² planes: ``tiny`` costs ~0.3 s a load on a busy 2-core machine) exported to
ONNX with its sidecar (``save_model_package``), and the same weights as torch files in both layouts
``load_encoder`` reads: ``lp3d export --weights``' (float16, with a super-resolution network) and a
training checkpoint's.

* ``test_mutated_sidecars``: the JSON's structure (keys dropped, duplicated, retyped, added; huge,
  negative, NaN and bool numbers; deep nesting; wrong list lengths; unicode junk) and its text
  (truncation, byte flips, a BOM, other documents).
* ``test_mutated_weights``: state dicts (missing and extra keys, int, tuple and bytes keys, wrong
  dtypes and shapes, non-finite and huge values, non-tensors), configurations, bounds, decoders,
  plane offsets, super-resolution entries and the sidecar a checkpoint falls back to.
* ``test_mutated_model_files``: ONNX bytes (flips, interesting values, truncation, appending),
  ONNX graphs edited with ``onnx`` (dims, types, attributes, initialisers, nodes, names, opsets) and
  ``.pt`` zips truncated, damaged or re-zipped with a damaged entry. onnxruntime and torch's zip
  reader run native code on these (a native hang ignores the in-process deadline, a crash ends the
  process), so this class runs in one worker process, under a 3 GiB address-space cap so that a huge
  allocation fails there: a hang or a crash of the worker is a failure naming its case.

Seeded (a numpy Generator per case): failures print the seed, the case and its mutations.
``LP3D_FUZZ_SEED`` picks another seed, ``LP3D_FUZZ_SCALE`` scales the counts, and
``LP3D_FUZZ_CASE=weights:17`` runs one case in this process with its full traceback.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from support.package_fuzzing import (
    ONLY,
    Case,
    Seeds,
    Worker,
    attempt,
    fuzz,
    in_process,
    make_seeds,
)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> Seeds:
    return make_seeds(tmp_path_factory.mktemp("seeds"))


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread() -> Any:
    """Tiny convolutions on two threads of a busy machine wait for each other (~0.5 s an image)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# ======================================================================================== mutations

NUMBERS: list[Any] = [
    0, -1, 1, 2, 3, 8, 16, 31, 32, 33, 64, 4096, 4097, 2**31, 2**63, 2**64, 10**40, 10**400,
    -(2**63), 0.5, -0.0, 1e-320, 1e308, -1e308, math.nan, math.inf, -math.inf, True, False,
]  # fmt: skip
STRINGS = [
    "", "\x00", "m\x00.onnx", "\ud800", "\udcff.onnx", "\u202exnno.m", "\U0001f600" * 3, "../m.onnx",
    "/etc/passwd", "m.json", "m.onnx", "m.superres.onnx", "NaN", "1e999", "lp3d-model-package", "tiny",
    "x" * 100_000, "C:\\m.onnx", ".", "\n",
]  # fmt: skip
OTHERS: list[Any] = [
    None, [], {}, [1, 2, 3], {"a": 1}, [[0.0] * 32] * 64, [0.0] * 33, [[1e38] * 32] * 64,
    "\x00NEST:3\x00", "\x00NEST:200\x00", "\x00NEST:100000\x00",
]  # fmt: skip
VALUES = NUMBERS + STRINGS + OTHERS
NEW_KEYS: list[Any] = ["superres", "model", "encoder_config", "input_name", "x", "decoder", "\ud800"]
#: A plausible ``superres`` entry whose file is never there.
SUPERRES = {
    "model": "x.onnx",
    "input_resolution": 8,
    "output_resolution": 16,
    "in_channels": 32,
    "sha256": "0" * 64,
}


def choice(rng: np.random.Generator, pool: Any) -> Any:
    pool = list(pool)
    return pool[int(rng.integers(len(pool)))]


def pick_path(rng: np.random.Generator, root: Any) -> list:
    """A random walk from ``root`` into its dicts and lists, stopping on the way with probability 0.35."""
    path: list = []
    node = root
    while isinstance(node, (dict, list)) and len(node) and (not path or rng.random() > 0.35):
        key = choice(rng, node.keys() if isinstance(node, dict) else range(len(node)))
        path.append(key)
        node = node[key]
    return path


def structure_op(rng: np.random.Generator, root: Any, values: list[Any]) -> str:
    """One mutation of a JSON-like tree, in place; returns what it did."""
    path = pick_path(rng, root)
    if not path:
        return "nothing"
    parent = root
    for key in path[:-1]:
        parent = parent[key]
    key, node = path[-1], parent[path[-1]]
    kind = choice(rng, ["drop", "retype", "number", "string", "resize", "add", "swap"])
    where = "/".join(k if isinstance(k, str) else _short(k) for k in path)[:80]
    if kind == "drop":
        del parent[key]
    elif kind in ("retype", "number", "string"):
        pool = {"retype": values, "number": NUMBERS, "string": STRINGS}[kind]
        parent[key] = tree_copy(choice(rng, pool))
        return f"{where} = {_short(parent[key])}"
    elif kind == "resize" and isinstance(node, list) and node:
        n = choice(rng, [0, 1, len(node) - 1, len(node) + 1, 2 * len(node)])
        parent[key] = (node * 3)[:n]
        return f"{where}: {len(node)} -> {n} items"
    elif kind == "add" or kind == "resize":
        target = node if isinstance(node, dict) else parent if isinstance(parent, dict) else root
        new = choice(rng, NEW_KEYS)
        target[new] = tree_copy(SUPERRES if new == "superres" and rng.random() < 0.5 else choice(rng, values))
        return f"add {_short(new)} = {_short(target[new])} under {where}"
    elif kind == "swap" and isinstance(parent, dict) and len(parent) > 1:
        other = choice(rng, parent.keys())
        parent[key], parent[other] = parent[other], parent[key]
        return f"swap {where} with {_short(other)}"
    return f"{kind} {where}"


def tree_copy(value: Any) -> Any:
    """A copy of the dicts and lists of ``value``, sharing the rest (mutations replace tensors and
    plain values, never change them in place)."""
    if isinstance(value, dict):
        return {k: tree_copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [tree_copy(v) for v in value]
    return value


def _short(value: Any) -> str:
    if isinstance(value, int) and value.bit_length() > 10_000:
        return f"an int of {value.bit_length()} bits"
    text = repr(value)
    return text if len(text) < 60 else f"{text[:50]}... ({len(text)} chars)"


def _nested(depth: int, *, text: bool) -> Any:
    if text:
        return "[" * depth + "]" * depth if depth % 2 else '{"a":' * depth + "1" + "}" * depth
    value: Any = []
    for _ in range(min(depth, 300)):  # real nesting: pickle and repr recurse
        value = [value]
    return value


def to_json(data: Any) -> bytes:
    text = json.dumps(data, allow_nan=True, default=repr, skipkeys=True)
    text = re.sub(r'"\\u0000NEST:(\d+)\\u0000"', lambda m: _nested(int(m.group(1)), text=True), text)
    return text.encode()


def unnest(value: Any) -> Any:
    """The NEST markers of ``VALUES`` as real nested lists (for pickling)."""
    if isinstance(value, str) and (m := re.fullmatch(r"\x00NEST:(\d+)\x00", value)):
        return _nested(int(m.group(1)), text=False)
    if isinstance(value, dict):
        return {k: unnest(v) for k, v in value.items()}
    if isinstance(value, list):
        return [unnest(v) for v in value]
    return value


WHOLE = [b"", b"null", b"[]", b"{}", b'"x"', b"1e999", b"NaN", b"{" * 100_000, b"\xff\xfe{}", b"\x00" * 64]
DUP_KEYS = ["image_size", "triplane_resolution", "decoder", "format", "format_version", "box_warp", "model"]


def text_op(rng: np.random.Generator, text: bytes) -> tuple[bytes, str]:
    kind = choice(rng, ["truncate", "flip", "dup-key", "bom", "whole", "append"])
    i = int(rng.integers(max(len(text), 1)))
    if kind == "truncate":
        return text[:i], f"text truncated at {i} of {len(text)}"
    if kind == "flip":
        b = bytearray(text)
        for j in rng.integers(len(b), size=int(rng.integers(1, 4))) if b else []:
            b[j] ^= 1 << int(rng.integers(8))
        return bytes(b), "text bytes flipped"
    if kind == "dup-key" and text.endswith(b"}"):
        key, value = choice(rng, DUP_KEYS), to_json(choice(rng, VALUES))
        pair = b'"%s": %s' % (key.encode(), value)
        if rng.random() < 0.5:
            return text[:-1] + b", " + pair + b"}", f"duplicate {key} last = {_short(value)}"
        return b"{" + pair + b", " + text[1:], f"duplicate {key} first = {_short(value)}"
    if kind == "bom":
        return b"\xef\xbb\xbf" + text, "UTF-8 BOM"
    if kind == "whole":
        new = choice(rng, WHOLE)
        return new, f"text = {_short(new)}"
    junk = choice(rng, [b"{}", b"\x00", b"garbage", b" " * 1000, text])
    return text + junk, f"appended {_short(junk)}"


# ============================================================================================ sidecars


def mutated_sidecar(rng: np.random.Generator, seed: dict[str, Any], ops: list[str]) -> tuple[bytes, Any]:
    data = json.loads(json.dumps(seed))  # a copy, at C speed
    for _ in range(int(rng.integers(1, 4))):
        ops.append(structure_op(rng, data, VALUES))
    text = to_json(data)
    if rng.random() < 0.25:
        text, op = text_op(rng, text)
        ops.append(op)
    return text, data


def make_sidecar_case(rng: np.random.Generator, seeds: Seeds, here: Path, case: Case) -> None:
    text, data = mutated_sidecar(rng, seeds.sidecar, case.ops)
    (here / "m.onnx").write_bytes(seeds.onnx)
    (here / "m.superres.onnx").write_bytes(seeds.sr_onnx)
    (here / "m.json").write_bytes(text)
    case.path = here / ("m.json" if rng.random() < 0.15 else "m.onnx")
    case.superres = isinstance(data, dict) and "superres" in data and rng.random() < 0.3
    case.ops.append(f"load {case.path.name}{' with superres' if case.superres else ''}")


def test_mutated_sidecars(seeds: Seeds, tmp_path: Path) -> None:
    fuzz("sidecars", make_sidecar_case, seeds, tmp_path, in_process)


# ============================================================================================= weights


def tensor_op(rng: np.random.Generator, t: Any) -> tuple[Any, str]:
    """A changed copy of the tensor ``t``: another dtype or shape, non-finite or huge values."""
    import torch

    kind = choice(rng, ["dtype", "shape", "nonfinite", "huge"])
    if kind == "dtype":
        dtype = choice(
            rng, [torch.int64, torch.bool, torch.complex64, torch.float64, torch.bfloat16, torch.uint8]
        )
        return t.to(dtype), f"dtype {dtype}"
    if kind == "shape":
        shapes = {
            "transposed": lambda: t.t() if t.ndim == 2 else t.reshape(1, -1),
            "unsqueezed": lambda: t[None],
            "one short": lambda: t.reshape(-1)[:-1],
            "empty": lambda: t.reshape(-1)[:0],
            "scalar": lambda: t.reshape(-1)[0].clone(),
            "doubled": lambda: torch.cat([t, t]) if t.ndim else t.repeat(2),
        }
        name = choice(rng, shapes)
        return shapes[name]().clone(), f"shape {name}"
    out = t.float().clone()
    value = choice(rng, [math.nan, math.inf, -math.inf] if kind == "nonfinite" else [1e30, 3e38, 65504.0])
    if out.numel() and rng.random() < 0.5:
        out.view(-1)[int(rng.integers(out.numel()))] = value
        return out, f"one value {value}"
    return out.fill_(value), f"all {value}"


def weights_op(rng: np.random.Generator, root: dict[str, Any]) -> str:
    """One mutation of a checkpoint, in place: tensors, state dicts and plain values."""
    import torch

    path = pick_path(rng, root)
    if not path:
        return "nothing"
    parent = root
    for key in path[:-1]:
        parent = parent[key]
    key, node = path[-1], parent[path[-1]]
    where = "/".join(k if isinstance(k, str) else _short(k) for k in path)[:80]
    if isinstance(node, torch.Tensor) and rng.random() < 0.8:
        parent[key], what = tensor_op(rng, node)
        return f"{where}: {what}"
    if isinstance(node, dict) and node and rng.random() < 0.5:
        kind = choice(rng, ["int keys", "odd key", "extra", "empty"])
        if kind == "int keys":
            parent[key] = dict(enumerate(node.values()))
        elif kind == "odd key":
            odd = choice(rng, [0, (1, 2), b"x", 1.5, None, 10**5000])
            node[odd] = node.pop(choice(rng, node.keys()))
            return f"{where}: a key becomes {_short(odd)}"
        elif kind == "extra":
            name = choice(rng, ["x", "encoder.extra", "backbone.extra.weight", "decoder.w2", "superres.x"])
            node[name] = torch.zeros(int(rng.integers(0, 4)))
        else:
            parent[key] = {}
        return f"{where}: {kind}"
    extra = [torch.zeros(3), torch.tensor(math.nan), np.zeros(3), 10**5000]  # pickle only: no JSON for these
    return structure_op(rng, root, VALUES + extra)


def make_weights_case(rng: np.random.Generator, seeds: Seeds, here: Path, case: Case) -> None:
    import torch

    layout = choice(rng, ["weights", "training"])
    ckpt = tree_copy(seeds.weights if layout == "weights" else seeds.training)
    texts = [k for k in ("config", "scene") if isinstance(ckpt.get(k), str)]
    for k in texts:
        ckpt[k] = json.loads(ckpt[k])
    case.ops.append(f"{layout} layout")
    if rng.random() < 0.2:  # the sidecar a checkpoint falls back to for its decoder and bounds
        dropped = choice(rng, [["decoder"], ["bounds", "scene"], ["decoder", "bounds", "scene"]])
        for k in dropped:
            ckpt.pop(k, None)
        if layout == "training" and "decoder" in dropped:
            ckpt["student"] = {k: v for k, v in ckpt["student"].items() if not k.startswith("decoder.")}
        ops = ["valid"]
        text = to_json(seeds.sidecar)
        if rng.random() < 0.5:
            text, _ = mutated_sidecar(rng, seeds.sidecar, ops := [])
        (here / "w.json").write_bytes(text)
        case.ops.append(f"without {dropped}, a sidecar ({'; '.join(ops)})")
    for _ in range(int(rng.integers(1, 4))):
        case.ops.append(weights_op(rng, ckpt))
    for k in texts:
        if isinstance(ckpt.get(k), (dict, list)):
            with contextlib.suppress(ValueError):  # a 5,000-digit int has no JSON: kept as it is
                ckpt[k] = to_json(ckpt[k]).decode()
    try:
        torch.save(unnest(ckpt), here / "w.pt")
    except Exception as e:  # something torch cannot save: no case
        case.ops.append(f"not saved: {type(e).__name__}")
        return
    case.path = here / "w.pt"
    case.superres = layout == "weights" and rng.random() < 0.4


def test_mutated_weights(seeds: Seeds, tmp_path: Path) -> None:
    fuzz("weights", make_weights_case, seeds, tmp_path, in_process)


# ====================================================================================== model files

INTERESTING = [0, 1, 0x7F, 0x80, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, 1 << 40, 2**64 - 1]


def byte_op(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    b = bytearray(data)
    i = int(rng.integers(max(len(b), 1)))
    kind = choice(rng, ["flip", "value", "truncate", "append", "splice", "zero"])
    if kind == "flip" and b:
        b[i] ^= 1 << int(rng.integers(8))
    elif kind == "value" and b:
        width = choice(rng, [1, 2, 4, 8])
        b[i : i + width] = choice(rng, INTERESTING).to_bytes(8, "little")[:width][: len(b) - i]
        return bytes(b), f"value at {i} (width {width})"
    elif kind == "truncate":
        return bytes(b[:i]), f"truncated at {i} of {len(b)}"
    elif kind == "append":
        junk = choice(rng, [b"\x00" * 16, bytes(rng.integers(0, 256, 64, dtype=np.uint8)), bytes(b[i:])])
        return bytes(b) + junk, f"appended {len(junk)} bytes"
    elif kind == "splice":
        n = int(rng.integers(1, 256))
        b[i:i] = b[i : i + n]
    elif kind == "zero":
        n = int(rng.integers(1, 4096))
        b[i : i + n] = bytes(len(b[i : i + n]))
    return bytes(b), f"{kind} at {i}"


_ONNX_SEED: dict[bytes, Any] = {}


def onnx_graph_op(rng: np.random.Generator, model: Any) -> str:
    """One edit of an ONNX ModelProto, in place, that keeps it a valid protobuf."""
    g = model.graph
    kind = choice(rng, ["dim", "type", "node", "init", "attr", "op", "names", "opset"])
    if kind == "dim":
        vi = choice(rng, [*g.input, *g.output])
        dims = vi.type.tensor_type.shape.dim
        d = dims[int(rng.integers(len(dims)))]
        if rng.random() < 0.2:
            d.dim_param = "n"
            return f"{vi.name}: a symbolic dim"
        d.dim_value = choice(rng, [0, 1, 2, 3, 7, 8, 31, 32, 33, 96, 2**31 - 1, 2**40])
        return f"{vi.name}: a dim = {d.dim_value}"
    if kind == "type":
        target = choice(rng, [*g.input, *g.output, *g.initializer])
        elem = int(choice(rng, [0, 1, 2, 6, 7, 9, 10, 11, 16, 99]))
        if hasattr(target, "data_type"):
            target.data_type = elem
        else:
            target.type.tensor_type.elem_type = elem
        return f"{target.name}: element type {elem}"
    if kind == "node":
        k = int(rng.integers(len(g.node)))
        if rng.random() < 0.5:
            del g.node[k]
            return f"node {k} removed"
        g.node.append(g.node[k])
        return f"node {k} duplicated"
    if kind == "init":
        return _init_op(rng, g)
    if kind == "attr":
        return _attr_op(rng, g)
    if kind == "op":
        node = choice(rng, g.node)
        node.op_type = choice(rng, ["Unknown", "Relu", "Conv", "Reshape", "Loop", "Identity", ""])
        if rng.random() < 0.3:
            node.domain = "com.example"
        return f"node {node.name}: op {node.op_type!r} domain {node.domain!r}"
    if kind == "names":
        vi = choice(rng, [*g.input, *g.output])
        vi.name = choice(rng, ["x", "", g.node[0].output[0], "\U0001f600"])
        return f"renamed an input/output to {vi.name!r}"
    model.opset_import[0].version = choice(rng, [1, 7, 13, 99, 10**6])
    model.ir_version = choice(rng, [model.ir_version, 0, 3, 99])
    return f"opset {model.opset_import[0].version}, ir {model.ir_version}"


def _init_op(rng: np.random.Generator, g: Any) -> str:
    init = choice(rng, g.initializer)
    what = choice(rng, ["remove", "dims", "values", "data"])
    if what == "remove":
        g.initializer.remove(init)
    elif what == "dims" and len(init.dims):
        j = int(rng.integers(len(init.dims)))
        init.dims[j] = choice(rng, [0, 1, 2, 2**31, 2**40, -1])
    elif what == "values" and init.raw_data and init.data_type == 1:
        values = np.frombuffer(init.raw_data, np.float32).copy()
        values[int(rng.integers(values.size))] = choice(rng, [math.nan, math.inf, 3e38, -1e30])
        init.raw_data = values.tobytes()
    elif init.raw_data:
        init.raw_data = init.raw_data[: int(rng.integers(len(init.raw_data)))]
    return f"initializer {init.name}: {what}"


def _attr_op(rng: np.random.Generator, g: Any) -> str:
    from onnx import AttributeProto, numpy_helper

    node = choice(rng, [n for n in g.node if n.attribute])
    a = choice(rng, node.attribute)
    huge = [0, -1, 1, 2, 1000, 2**31 - 1, 2**62]
    if a.type == AttributeProto.INT:
        a.i = choice(rng, huge)
    elif a.type == AttributeProto.INTS and a.ints:
        a.ints[int(rng.integers(len(a.ints)))] = choice(rng, huge)
    elif a.type == AttributeProto.FLOAT:
        a.f = choice(rng, [0.0, -1.0, 1e30, math.nan, math.inf])
    elif a.type == AttributeProto.TENSOR:
        arr = numpy_helper.to_array(a.t).copy()
        if arr.size:
            arr.reshape(-1)[int(rng.integers(arr.size))] = choice(rng, [0, -1, 2**20, 2**31 - 1])
            a.t.CopyFrom(numpy_helper.from_array(arr, a.t.name))
    elif a.type == AttributeProto.STRING:
        a.s = choice(rng, [b"", b"bogus", b"\xff" * 8])
    return f"node {node.name} ({node.op_type}): attribute {a.name}"


def make_file_case(rng: np.random.Generator, seeds: Seeds, here: Path, case: Case) -> None:
    kind = choice(rng, ["onnx bytes", "onnx graph", "onnx graph", "sr graph", "pt bytes", "pt entry"])
    case.ops.append(kind)
    if kind.startswith("pt"):
        data = _saved(seeds.weights)
        if kind == "pt entry":
            data = _mutate_entry(rng, data, case.ops)
        for _ in range(int(rng.integers(1, 3)) if kind == "pt bytes" else 0):
            data, op = byte_op(rng, data)
            case.ops.append(op)
        (here / "w.pt").write_bytes(data)
        case.path = here / "w.pt"  # without its SR: building one imports torch._dynamo (~3 s a worker)
        return
    sr = kind == "sr graph"
    data = seeds.sr_onnx if sr else seeds.onnx
    if kind != "onnx bytes":
        import onnx

        model = onnx.ModelProto()
        model.CopyFrom(_ONNX_SEED.get(data) or _ONNX_SEED.setdefault(data, onnx.load_from_string(data)))
        for _ in range(int(rng.integers(1, 3))):
            case.ops.append(onnx_graph_op(rng, model))
        data = model.SerializeToString()
    for _ in range(int(rng.integers(1, 4)) if kind == "onnx bytes" or rng.random() < 0.2 else 0):
        data, op = byte_op(rng, data)
        case.ops.append(op)
    sidecar = json.loads(json.dumps(seeds.sidecar))
    if sr:  # the network's SHA-256 as an export would record it: the damage reaches onnxruntime
        sidecar["superres"]["sha256"] = hashlib.sha256(data).hexdigest()
    (here / "m.onnx").write_bytes(seeds.onnx if sr else data)
    (here / "m.superres.onnx").write_bytes(data if sr else seeds.sr_onnx)
    (here / "m.json").write_bytes(to_json(sidecar))
    case.path, case.superres = here / "m.onnx", sr or bool(rng.random() < 0.3)


_SAVED: dict[int, bytes] = {}


def _saved(ckpt: dict[str, Any]) -> bytes:
    import torch

    if id(ckpt) not in _SAVED:
        buf = io.BytesIO()
        torch.save(ckpt, buf)
        _SAVED[id(ckpt)] = buf.getvalue()
    return _SAVED[id(ckpt)]


def _mutate_entry(rng: np.random.Generator, data: bytes, ops: list[str]) -> bytes:
    """One entry of a ``.pt`` zip (the pickle, a tensor's storage, the version) mutated, the zip written
    again with valid CRCs, so the damage reaches torch's unpickler and storage reader."""
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        entries = [(info.filename, z.read(info)) for info in z.infolist()]
    k = choice(
        rng,
        [i for i, (name, _) in enumerate(entries) if name.endswith("data.pkl")] * 3 + [*range(len(entries))],
    )
    name, body = entries[k]
    for _ in range(int(rng.integers(1, 3))):
        body, op = byte_op(rng, body)
        ops.append(f"{name.split('/', 1)[-1]}: {op}")
    entries[k] = (name, body)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as z:
        for name, body in entries:
            z.writestr(name, body)
    return out.getvalue()


@pytest.fixture(scope="module", autouse=True)
def worker(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Worker]:
    """The worker of ``test_mutated_model_files``, started with the module's first test when that test
    is to run."""
    w = Worker(tmp_path_factory.mktemp("worker") / "worker.log")
    if not ONLY and any(item.name == "test_mutated_model_files" for item in request.session.items):
        w.spawn()
    yield w
    w.close()


def test_mutated_model_files(seeds: Seeds, tmp_path: Path, worker: Worker) -> None:
    fuzz("files", make_file_case, seeds, tmp_path, in_process if ONLY else worker)


def test_the_seeds_load_and_encode(seeds: Seeds, tmp_path: Path) -> None:
    """The fuzzer's starting points are valid packages (else every case would be refused)."""
    import torch

    from lp3d.lift.inference import load_encoder

    (tmp_path / "m.onnx").write_bytes(seeds.onnx)
    (tmp_path / "m.superres.onnx").write_bytes(seeds.sr_onnx)
    (tmp_path / "m.json").write_bytes(to_json(seeds.sidecar))
    torch.save(seeds.weights, tmp_path / "w.pt")
    torch.save(seeds.training, tmp_path / "t.pt")
    for name in ("m.onnx", "m.json", "w.pt", "t.pt"):
        assert attempt(tmp_path / name, superres=True) == "ok", name
    assert load_encoder(tmp_path / "m.onnx", superres=True).superres is not None
    assert load_encoder(tmp_path / "w.pt", superres=True).superres is not None
