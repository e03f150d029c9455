"""Time the shipped encoder with onnxruntime: milliseconds per image, batch 1, on the machine it runs on.

    python bench/encode_speed.py                       # the shipped python/lp3d/lift/models/small.onnx
    python bench/encode_speed.py --model model.onnx --threads 2 --repeats 50
    python bench/encode_speed.py --flip-average        # lp3d encode --flip-average: one call, batch 2

Prints the median, minimum and maximum over ``--repeats`` runs after ``--warmup`` runs, the model's
file size and onnxruntime's version, as one markdown table row (``--header`` adds the header).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from lp3d.lift.flip_average import flip_averaged
    from lp3d.lift.inference import DEFAULT_MODEL

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="ONNX encoder (default: shipped)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument(
        "--flip-average", action="store_true", help="time lp3d encode --flip-average's encoding of one image"
    )
    p.add_argument("--header", action="store_true", help="print the table header too")
    args = p.parse_args(argv)

    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = args.threads
    t0 = time.perf_counter()
    session = ort.InferenceSession(str(args.model), opts, providers=["CPUExecutionProvider"])
    load_s = time.perf_counter() - t0
    (inp,) = session.get_inputs()
    size = int(inp.shape[-1])
    image = np.random.default_rng(0).uniform(-1, 1, (1, 3, size, size)).astype(np.float32)

    def encode(images: np.ndarray) -> np.ndarray:
        return session.run(None, {inp.name: images})[0]

    def once() -> None:
        flip_averaged(encode, image) if args.flip_average else encode(image)

    for _ in range(args.warmup):
        once()
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        once()
        times.append(1000 * (time.perf_counter() - t))
    if args.header:
        print("| model | MB | onnxruntime | threads | load s | ms/image median | min | max | load avg |")
        print("|---|---|---|---|---|---|---|---|---|")
    mb = args.model.stat().st_size / 1e6
    load = os.getloadavg()[0]
    name = args.model.name + (", flip-averaged" if args.flip_average else "")
    print(
        f"| {name} | {mb:.1f} | {ort.__version__} | {args.threads} | {load_s:.2f} | "
        f"{statistics.median(times):.1f} | {min(times):.1f} | {max(times):.1f} | {load:.2f} |"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
