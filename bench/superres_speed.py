"""Time the super-resolution network per image: the renderer's WGSL kernels (``lp3d_render.SuperRes``,
on whatever adapter lp3d_render picked: lavapipe here) against onnxruntime on the same ONNX file, in
one process, pairs back to back, batch 1.

    python bench/superres_speed.py                     # the shipped 64² -> 256² and EG3D's 128² -> 512²
    python bench/superres_speed.py --shapes student --repeats 5

``student`` is the shipped package's ``small.superres.onnx``; ``eg3d`` is a network of EG3D's
``SuperresolutionHybrid8XDC`` shape (32 channels, widths 256 and 128, 128² -> 512²) with random
weights, exported to ONNX in a temporary folder as ``lp3d export`` does. Both are read back with
``read_superres_onnx`` and handed to the GPU as a package's would be. Prints one markdown table row per
shape (median seconds per image of each, their ratio, and the largest difference between the two
outputs), after one untimed run of each (pipeline compile, onnxruntime's first run).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

SHAPES = ("student", "eg3d")


def _eg3d_onnx(folder: Path) -> Path:
    import torch

    from lp3d.export import export_superres
    from lp3d.nets.superres import SuperresConfig, SuperResolution

    torch.manual_seed(0)
    sr = SuperResolution(SuperresConfig()).eval()
    with torch.no_grad():  # EG3D starts its biases at zero; a trained network's are not
        for name, p in sr.named_parameters():
            if name.endswith(".bias") and ".affine." not in name:
                p.normal_(0.0, 0.1)
    return export_superres(sr, folder / "eg3d.superres.onnx")


def main(argv: list[str] | None = None) -> int:
    import onnxruntime as ort

    import lp3d_render
    from lp3d.lift.gpu_superres import gpu_superres
    from lp3d.lift.inference import DEFAULT_MODEL
    from lp3d.lift.model_package import load_model_package
    from lp3d.nets.superres_onnx import read_superres_onnx

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shapes", nargs="+", choices=SHAPES, default=list(SHAPES))
    p.add_argument("--repeats", type=int, default=3, help="timed pairs per shape")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    args = p.parse_args(argv)

    info = lp3d_render.adapter_info()
    print(f"adapter: {info['name']} ({info['device_type']}); onnxruntime {ort.__version__}")
    print("| shape | WGSL s/image | onnxruntime s/image | WGSL / onnxruntime | max abs diff |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for shape in args.shapes:
            if shape == "student":
                package = load_model_package(DEFAULT_MODEL)
                assert package.superres is not None, "the shipped package has no super-resolution network"
                path = package.superres.path
            else:
                path = _eg3d_onnx(Path(tmp))
            sr = gpu_superres(read_superres_onnx(path))
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = args.threads
            session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
            name = session.get_inputs()[0].name
            r = sr.input_resolution
            x = np.random.default_rng(0).uniform(-1, 1, (1, sr.in_channels, r, r)).astype(np.float32)
            got, want = sr.apply(x), session.run(None, {name: x})[0]  # untimed: compile, first run
            wgsl, onnx = [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                sr.apply(x)
                wgsl.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                session.run(None, {name: x})
                onnx.append(time.perf_counter() - t0)
            w, o = statistics.median(wgsl), statistics.median(onnx)
            label = f"{shape} {r}² → {sr.output_resolution}²"
            err = float(np.abs(got - want).max())
            print(f"| {label} | {w:.3f} | {o:.3f} | {w / o:.1f}× | {err:.1e} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
