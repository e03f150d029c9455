"""Is the procedural teacher a fair stand-in for EG3D? Three checks on held-out identities, per version.

    python bench/teacher_check.py --versions 1 2        # about 6 min on a quiet 2-core CPU

* **Resolvable by its sampler**: each head (the teacher's native 256² planes) rendered at 128² with
  EG3D's 48+48 samples against 192+192, from the evaluation's novel views (yaw -30/0/30 at pitch 0,
  yaw 0 at pitch 20). PSNR (RGB in [0, 1]) and the largest single-pixel error. Target:
  >= 40 dB, <= 0.15.
* **Plane-noise sensitivity**: the teacher's own 64² planes plus i.i.d. Gaussian noise of 2/5/10/20 %
  of each (plane, channel)'s std over the texels, rendered at 64² with 24+24 samples from yaw -30/0/30
  at pitch 15, scored against the clean render. What a student's plane error of that size costs.
  Target at 10 %: >= 28 dB.
* **Variety** (same planes, views and samples, noise-free): PSNR of the mean triplane of the
  identities against each identity ("mean head"), and of each identity against every other ("other
  head"). A teacher whose heads all look alike scores high on both; v2 may not exceed v1 by > 1 dB.

Prints a Markdown table per check (and the command) to stdout; ``--json`` writes the numbers.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from lp3d.evaluation.protocol import NOVEL_VIEWS
from lp3d.render.camera import look_at_camera
from lp3d.render.native import render
from lp3d.render.psnr import psnr_db
from lp3d.render.triplane import TriplaneData
from lp3d.teachers.procedural import TEACHER_VERSIONS, ProceduralTeacher
from lp3d.training.config import TrainConfig

#: Held-out identities (TrainConfig.eval_seed_start; no configuration trains on them).
EVAL_SEED_START = TrainConfig.__dataclass_fields__["eval_seed_start"].default

NOISE_LEVELS = (0.02, 0.05, 0.10, 0.20)
NOISE_VIEWS = ((-30.0, 15.0), (0.0, 15.0), (30.0, 15.0))


def cameras(views: tuple[tuple[float, float], ...]) -> np.ndarray:
    return np.stack([look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in views])


def rgb(tri: TriplaneData, cams: np.ndarray, resolution: int, samples: int) -> np.ndarray:
    out = render(
        tri,
        cams,
        resolution=resolution,
        depth_resolution=samples,
        depth_resolution_importance=samples,
        outputs=["rgb"],
    )
    return out["rgb"]


def with_planes(tri: TriplaneData, planes: np.ndarray) -> TriplaneData:
    return dataclasses.replace(tri, planes=planes.astype(np.float32))


def convergence(version: int, seeds: list[int]) -> dict[str, list[float]]:
    teacher = ProceduralTeacher(version=version)
    cams = cameras(NOVEL_VIEWS)
    psnrs, worst = [], []
    for seed in seeds:
        tri = teacher.sample(seed)
        low = rgb(tri, cams, 128, 48)
        high = rgb(tri, cams, 128, 192)
        psnrs.append(psnr_db(low, high))
        worst.append(float(np.max(np.abs(np.clip(low, -1, 1) - np.clip(high, -1, 1))) / 2.0))
    return {"psnr": psnrs, "max_error": worst}


def noise_and_variety(version: int, seeds: list[int], noise_seed: int) -> dict[str, object]:
    teacher = ProceduralTeacher(resolution=64, version=version)
    cams = cameras(NOISE_VIEWS)
    rng = np.random.default_rng(noise_seed)
    tris = [teacher.sample(s) for s in seeds]
    clean = [rgb(t, cams, 64, 24) for t in tris]
    noisy: dict[str, float] = {}
    for level in NOISE_LEVELS:
        scores = []
        for tri, ref in zip(tris, clean, strict=True):
            std = tri.planes.std(axis=(2, 3), keepdims=True)
            planes = tri.planes + level * std * rng.standard_normal(tri.planes.shape)
            scores.append(psnr_db(rgb(with_planes(tri, planes), cams, 64, 24), ref))
        noisy[f"{level:.2f}"] = float(np.mean(scores))
    mean_tri = with_planes(tris[0], np.mean([t.planes for t in tris], axis=0))
    mean_render = rgb(mean_tri, cams, 64, 24)
    mean_head = float(np.mean([psnr_db(mean_render, c) for c in clean]))
    other = [psnr_db(clean[i], clean[j]) for i in range(len(seeds)) for j in range(len(seeds)) if i != j]
    return {"noise": noisy, "mean_head": mean_head, "other_head": float(np.mean(other))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--versions", type=int, nargs="+", default=list(TEACHER_VERSIONS))
    p.add_argument("--n-heads", type=int, default=8, help="held-out heads for the sampler check")
    p.add_argument("--n-identities", type=int, default=16, help="held-out identities for noise/variety")
    p.add_argument("--noise-seed", type=int, default=0)
    p.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = p.parse_args(argv)
    start = EVAL_SEED_START
    results: dict[int, dict[str, object]] = {}
    for version in args.versions:
        t0 = time.perf_counter()
        conv = convergence(version, list(range(start, start + args.n_heads)))
        rest = noise_and_variety(version, list(range(start, start + args.n_identities)), args.noise_seed)
        results[version] = {"convergence": conv, **rest, "seconds": time.perf_counter() - t0}
        print(f"v{version}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)

    print(f"Command: `python bench/teacher_check.py --versions {' '.join(map(str, args.versions))}`\n")
    print(f"48+48 against 192+192, 128², {args.n_heads} held-out heads (seeds {start}..), 4 novel views\n")
    print("| teacher | mean PSNR | worst head PSNR | largest pixel error |")
    print("|---|---|---|---|")
    for v, r in results.items():
        c = r["convergence"]
        mean, worst, err = np.mean(c["psnr"]), np.min(c["psnr"]), np.max(c["max_error"])
        print(f"| v{v} | {mean:.1f} dB | {worst:.1f} dB | {err:.3f} |")
    print(f"\nPlane noise and variety: 64² planes, 64² renders at 24+24, {args.n_identities} identities\n")
    levels = " | ".join(f"noise {int(100 * x)} %" for x in NOISE_LEVELS)
    print(f"| teacher | {levels} | mean head | other head |")
    print("|---|" + "---|" * (len(NOISE_LEVELS) + 2))
    for v, r in results.items():
        cells = " | ".join(f"{x:.1f} dB" for x in r["noise"].values())  # type: ignore[union-attr]
        print(f"| v{v} | {cells} | {r['mean_head']:.1f} dB | {r['other_head']:.1f} dB |")
    if args.json is not None:
        args.json.write_text(json.dumps({f"v{v}": r for v, r in results.items()}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
