"""The machinery of the model-package fuzzer (``tests/robustness/test_package_fuzz.py``): its seeds
(a valid ``micro`` package in every layout the loader reads), one case run end to end through the
public loader, the run of a class of cases, and the worker process that runs the cases whose native
code may hang or crash."""

import json
import os
import re
import select
import shutil
import subprocess
import sys
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from support.deadline import Hang, deadline
from support.paths import TESTS

SCALE = float(os.environ.get("LP3D_FUZZ_SCALE", "1"))
SEED = int(os.environ.get("LP3D_FUZZ_SEED", "25"))
ONLY = os.environ.get("LP3D_FUZZ_CASE")
#: Cases per class and run (docs/reliability.md quotes them).
CASES = {"sidecars": round(100 * SCALE), "weights": round(80 * SCALE), "files": round(80 * SCALE)}
#: A case running longer than this is a hang (normal cases take well under a second).
DEADLINE_S = 30.0
#: The worker's address space beyond what its imports took.
MEMORY_CAP = 3 << 30
#: A loaded package is run only up to this image and triplane side (the caps allow 4096 and 2048:
#: a package's right, but seconds and GiBs a case here).
RUN_CAP = 256
#: A clear error is short: no sidecar, array or junk string dumped into it.
MAX_MESSAGE = 2000


# ============================================================================================== seeds


@dataclass(frozen=True, repr=False)
class Seeds:
    onnx: bytes
    sr_onnx: bytes
    sidecar: dict[str, Any]
    weights: dict[str, Any]
    training: dict[str, Any]


def micro_config() -> Any:
    from lp3d.nets.encoder import EncoderConfig

    return EncoderConfig(
        name="micro",
        image_size=32,
        triplane_resolution=8,
        feature_resolution=8,
        backbone_widths=(4, 4, 8, 8),
        backbone_depths=(1, 1, 1, 1),
        aspp_channels=8,
        aspp_rates=(1, 2, 3),
        aspp_dropout=0.0,
        low_embed_dim=8,
        low_depth=1,
        low_heads=1,
        low_conv_channels=8,
        feature_channels=8,
        high_source="backbone",
        high_stem_channels=4,
        high_channels=8,
        high_convs=1,
        head_in_channels=(8,),
        head_embed_dim=8,
        head_heads=1,
        head_sr_ratio=1,
        head_out_channels=(8,),
    )


def make_seeds(folder: Path) -> Seeds:
    import torch

    from lp3d.export.superres import package_superres
    from lp3d.lift.model_package import save_model_package
    from lp3d.nets.encoder import build_encoder
    from lp3d.nets.superres import SuperresConfig, SuperResolution
    from lp3d.render.sample_scenes import coloured_sphere

    torch.manual_seed(0)
    cfg = micro_config()
    enc = build_encoder(cfg).eval()
    path = folder / "m.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # legacy-exporter deprecation and tracer warnings
        torch.onnx.export(
            enc,
            (torch.zeros(1, 3, cfg.image_size, cfg.image_size),),
            str(path),
            input_names=["image"],
            output_names=["planes"],
            dynamic_axes={"image": {0: "batch"}, "planes": {0: "batch"}},
            dynamo=False,
        )
    tri = coloured_sphere(size=8)
    decoder = {k: torch.from_numpy(getattr(tri, k).copy()) for k in ("w0", "b0", "w1", "b1")}
    bounds = {"box_warp": tri.box_warp, "ray_start": tri.ray_start, "ray_end": tri.ray_end}
    sr = SuperResolution(
        SuperresConfig(name="t", input_resolution=8, output_resolution=16, block_channels=(4,), w_dim=4)
    )
    entry, _ = package_superres(sr, path)
    side = save_model_package(path, decoder, cfg, bounds, superres=entry)
    state = {k: v.detach().clone() for k, v in enc.state_dict().items()}
    weights = {
        "format": "lp3d-encoder-weights-v1",
        "config": cfg.to_dict(),
        "encoder": {k: v.half() for k, v in state.items()},
        "plane_offset": None,
        "decoder": decoder,
        "bounds": bounds,
        "superres": {"config": sr.config.to_dict(), "state": sr.state_dict()},
    }
    student = {f"encoder.{k}": v for k, v in state.items()}
    student.update({f"decoder.{k}": v for k, v in decoder.items()})
    student["plane_offset"] = torch.zeros(3, 32, 8, 8)
    training = {
        "format": "lp3d-train-checkpoint-v1",
        "config": json.dumps({"name": "micro-cpu", "recipe": "cpu", "encoder": cfg.to_dict()}),
        "scene": json.dumps(bounds),
        "step": 1,
        "student": student,
    }
    sr_onnx = (folder / "m.superres.onnx").read_bytes()
    return Seeds(path.read_bytes(), sr_onnx, json.loads(side.read_text()), weights, training)


# ============================================================================= one case, end to end


def attempt(path: Path, superres: bool = False) -> str:
    """Load ``path`` with the public loader and use what loads: ``"ok"`` (or how far it went) or
    ``"refused"`` for a ModelPackageError that names the file and is short. Any other exception, and
    an unclear error (AssertionError), propagates."""
    from lp3d.lift.inference import load_encoder
    from lp3d.lift.model_package import ModelPackageError, load_model_package

    folder = path.parent
    try:
        if path.suffix == ".json":
            path = load_model_package(path).model_path
            if not path.is_file():
                return "ok (sidecar only)"
        enc = load_encoder(path, superres=superres)
        pkg = enc.package
        if max(pkg.image_size, pkg.triplane_resolution) > RUN_CAP:
            return "ok (not run: large)"
        x = np.random.default_rng(0).uniform(-1, 1, (1, 3, pkg.image_size, pkg.image_size))
        planes = enc.run(x.astype(np.float32))
        pkg.triplane(planes[0], source="fuzz")
        sr = enc.superres
        if sr is not None and sr.input_resolution <= RUN_CAP:
            sr(np.zeros((sr.in_channels, sr.input_resolution, sr.input_resolution), np.float32))
    except ModelPackageError as e:
        message = str(e)
        if str(folder) not in message:
            raise AssertionError(f"the error names no file: {message[:300]!r}") from e
        if len(message) > MAX_MESSAGE:
            raise AssertionError(f"a {len(message)}-character error: {message[:300]!r}...") from e
        return "refused"
    return "ok"


@dataclass
class Case:
    klass: str
    index: int
    ops: list[str]
    path: Path | None = None
    superres: bool = False

    def __str__(self) -> str:
        text = f"{self.klass}:{self.index} (LP3D_FUZZ_SEED={SEED}) {'; '.join(self.ops)}"
        return text.encode("ascii", "backslashreplace").decode()


Maker = Callable[[np.random.Generator, Seeds, Path, Case], None]
CLASS_IDS = {"sidecars": 1, "weights": 2, "files": 3}


def cases(klass: str) -> list[int]:
    if ONLY:
        name, _, index = ONLY.partition(":")
        return [int(index)] if name == klass else []
    return list(range(CASES[klass]))


def fuzz(klass: str, make: Maker, seeds: Seeds, folder: Path, run: Callable[[Case], str]) -> Counter:
    """Every case of ``klass``: made, run, its outcome counted; failures collected and reported
    together, each with what reproduces it."""
    outcomes: Counter[str] = Counter()
    failures: list[str] = []
    for i in cases(klass):
        case = Case(klass, i, [])
        here = folder / f"{klass}-{i}"
        here.mkdir()
        make(np.random.default_rng([SEED, CLASS_IDS[klass], i]), seeds, here, case)
        if case.path is None:
            outcomes["not made"] += 1
            continue
        try:
            outcomes[run(case)] += 1
        except Exception as e:
            if ONLY:
                raise
            failures.append(f"{case}\n    {type(e).__name__}: {str(e)[:500]}\n{tail(e)}")
            continue
        shutil.rmtree(here, ignore_errors=True)
    print(f"{klass}: {sum(outcomes.values())} cases, {dict(outcomes)}")
    if failures:
        pytest.fail(
            f"{len(failures)} of {len(cases(klass))} cases failed:\n\n" + "\n\n".join(failures[:25]),
            pytrace=False,
        )
    return outcomes


def tail(e: BaseException) -> str:
    if isinstance(e, WorkerFailure):
        return e.detail
    return "".join(traceback.format_exception(type(e), e, e.__traceback__)[-4:])


def in_process(case: Case) -> str:
    """A case in this process, under a deadline (Python loops: a native hang is the worker's to catch)."""
    assert case.path is not None
    try:
        with deadline(DEADLINE_S):
            return attempt(case.path, case.superres)
    except Hang as e:
        raise AssertionError(str(e)) from None


# ============================================================================================ worker


class WorkerFailure(Exception):
    """A case that the worker answered with another exception, or that hung or crashed it."""

    def __init__(self, message: str, detail: str = "") -> None:
        super().__init__(message)
        self.detail = detail


class Worker:
    """A process that runs :func:`attempt` on the paths it is sent, one JSON line each way; replaced
    after a case hangs or crashes it."""

    def __init__(self, log: Path) -> None:
        self.log = log
        self.proc: subprocess.Popen | None = None
        self.buf, self.ready = b"", False

    def spawn(self) -> None:
        """Start the process (its imports take seconds: they overlap the other tests)."""
        path = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
        with open(self.log, "ab") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", "from support.package_fuzzing import serve; serve()"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=err,
                env={**os.environ, "PYTHONPATH": path},
            )
        self.buf, self.ready = b"", False

    def _line(self, deadline: float) -> bytes:
        assert self.proc is not None and self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        while b"\n" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            if select.select([fd], [], [], left)[0]:
                chunk = os.read(fd, 1 << 16)
                if not chunk:
                    raise EOFError
                self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line

    def __call__(self, case: Case) -> str:
        if self.proc is None or self.proc.poll() is not None:
            self.spawn()
        if not self.ready and self._line(time.monotonic() + 300) != b"ready":
            raise RuntimeError(
                f"the fuzz worker did not start: {self.log.read_text(errors='replace')[-1500:]}"
            )
        self.ready = True
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(
            json.dumps({"path": str(case.path), "superres": case.superres}).encode() + b"\n"
        )
        self.proc.stdin.flush()
        try:
            reply = json.loads(self._line(time.monotonic() + DEADLINE_S))
        except (TimeoutError, EOFError) as e:
            self.close()
            what = f"hung (no answer in {DEADLINE_S:.0f} s)" if isinstance(e, TimeoutError) else "crashed"
            tail = self.log.read_text(errors="replace")[-1500:]
            raise WorkerFailure(f"the worker {what}, exit status {self.proc.returncode}", tail) from None
        if "error" in reply:
            raise WorkerFailure(reply["error"], reply["traceback"])
        return reply["outcome"]

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait()


def serve() -> None:
    """The worker's loop (``python -c "from support.package_fuzzing import serve; serve()"``)."""
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # whatever a library prints goes to the log, not into the answers
    import onnxruntime  # noqa: F401
    import torch

    import lp3d.lift.inference  # noqa: F401

    torch.set_num_threads(1)
    try:
        import resource

        vm = int(re.search(rb"VmSize:\s+(\d+)", Path("/proc/self/status").read_bytes()).group(1)) << 10
        resource.setrlimit(resource.RLIMIT_AS, (vm + MEMORY_CAP, resource.RLIM_INFINITY))
    except (ImportError, OSError, AttributeError):
        pass  # not Linux: no cap
    out.write(b"ready\n")
    for line in sys.stdin.buffer:
        request = json.loads(line)
        try:
            reply = {"outcome": attempt(Path(request["path"]), request["superres"])}
        except BaseException as e:
            text = "".join(traceback.format_exception(type(e), e, e.__traceback__)[-4:])
            reply = {"error": f"{type(e).__name__}: {str(e)[:500]}", "traceback": text[-3000:]}
        out.write(json.dumps(reply).encode() + b"\n")
