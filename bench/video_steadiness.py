"""How steady is ``lp3d video``? A hand-held clip of a teacher head, lifted with and without smoothing.

    python bench/video_steadiness.py                  # about 4 min on a 2-core CPU (48 frames)

**The clip.** A held-out head of the default procedural teacher turns slowly (yaw -15° to +15°) while
it changes a little towards a second head (the planes move 15% of the way: a slow real change that
the output *should* follow, so the teacher's own flicker is not zero). A hand-held camera films it:
the principal point wanders (a random walk, about 1.5 px per frame at 128², held within ±4 px), the
focal length breathes by ±1%, and every frame gets sensor noise (σ = 2/255). Rendered by
``lp3d_render`` at 128² with 48+48 samples, written to MP4 as a phone would.

**Scored**, for each variant of ``lp3d video CLIP --no-detect --yaw 30 --raw`` (no detection, so the
jitter reaches the encoder as it is; the new view is fixed, so all its motion is the head's own):

* flicker: the mean absolute change between consecutive output frames (0-255), and the same for
  the teacher's own head seen from that view on the same frames, through the same MP4 encoder;
* error: PSNR of each output frame against the teacher's own frame, averaged.

Prints a Markdown table for ``bench/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import lp3d_render
from lp3d.cli import main as lp3d_main
from lp3d.images import rgb_to_uint8
from lp3d.outputs import VideoWriter
from lp3d.photo.video import read_video
from lp3d.render.camera import FFHQ_FOCAL, look_at_camera
from lp3d.render.native import native_triplane
from lp3d.render.psnr import psnr_db
from lp3d.teachers.procedural import ProceduralTeacher

#: Two held-out identities (``TrainConfig.eval_seed_start`` + 200 ..): the head and the one it morphs to.
SEEDS = (1_000_200, 1_000_201)
VIEW_YAW = 30.0
SIZE = 128


def _render(tri, cams: np.ndarray, samples: int) -> list[np.ndarray]:
    out = lp3d_render.render(
        native_triplane(tri),
        cams,
        resolution=SIZE,
        depth_resolution=samples,
        depth_resolution_importance=samples,
        outputs=["rgb"],
    )
    return [rgb_to_uint8(x) for x in out["rgb"]]


def make_clip(frames: int, seed: int) -> tuple[list[np.ndarray], list]:
    """The hand-held frames (uint8) and the triplane of the head in each."""
    teacher = ProceduralTeacher()
    a, b = (teacher.sample(s) for s in SEEDS)
    rng = np.random.default_rng(seed)
    walk = np.zeros(2)
    clip, heads = [], []
    for t in range(frames):
        s = t / max(frames - 1, 1)
        tri = dataclasses.replace(
            a, planes=((1 - 0.15 * s) * a.planes + 0.15 * s * b.planes).astype(np.float32)
        )
        walk = np.clip(walk + rng.normal(0, 1.5, 2), -4, 4)
        cx, cy = 0.5 + walk / SIZE
        focal = FFHQ_FOCAL * (1 + 0.01 * np.sin(2 * np.pi * t / 17))
        cam = look_at_camera(yaw_deg=-15 + 30 * s, pitch_deg=5.0, focal=focal, cx=cx, cy=cy)
        frame = _render(tri, cam[None], 48)[0].astype(np.float64)
        frame += rng.normal(0, 2.0, frame.shape)
        clip.append(np.clip(np.round(frame), 0, 255).astype(np.uint8))
        heads.append(tri)
    return clip, heads


def _write(path: Path, frames: list[np.ndarray], fps: float = 25.0) -> None:
    writer = VideoWriter(path, ".mp4", fps)
    for f in frames:
        writer.add(f)
    writer.close()


def _read(path: Path) -> np.ndarray:
    return np.stack(list(read_video(path, None)[1])).astype(np.float64)


def flicker(frames: np.ndarray) -> float:
    return float(np.abs(np.diff(frames, axis=0)).mean())


def frame_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """:func:`lp3d.render.psnr.psnr_db` of two 8-bit frames, mapped onto the renderer's [-1, 1]."""
    return psnr_db(a / 127.5 - 1.0, b / 127.5 - 1.0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=48)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--samples", type=int, default=24, help="samples per ray of the lifted renders (+ as many)"
    )
    p.add_argument("--model", default=None, help="model package (default: the shipped one)")
    p.add_argument(
        "--variants",
        default="--steady 0;--smooth 0.5 --steady 0;--steady 1;--steady 2;--steady 3",
        help="';'-separated extra options of lp3d video, one run each",
    )
    args = p.parse_args(argv)

    t0 = time.perf_counter()
    clip, heads = make_clip(args.frames, args.seed)
    view = look_at_camera(yaw_deg=VIEW_YAW)[None]
    truth = [_render(tri, view, args.samples)[0] for tri in heads]
    print(f"clip: {args.frames} frames made in {time.perf_counter() - t0:.0f} s")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        src, ref = Path(tmp) / "clip.mp4", Path(tmp) / "teacher.mp4"
        _write(src, clip)
        _write(ref, truth)
        teacher_frames = _read(ref)
        f_teacher = flicker(teacher_frames)
        for variant in args.variants.split(";"):
            out = Path(tmp) / "out.mp4"
            cmd = ["video", str(src), "-o", str(out), "--no-detect", "--yaw", str(VIEW_YAW), "--raw"]
            cmd += [
                "--resolution",
                str(SIZE),
                "--samples",
                f"{args.samples}+{args.samples}",
                *variant.split(),
            ]
            cmd += ["--model", args.model] if args.model else []
            t0 = time.perf_counter()
            if lp3d_main(cmd) != 0:
                raise SystemExit(f"lp3d {' '.join(cmd)} failed")
            seconds = time.perf_counter() - t0
            lifted = _read(out)
            err = statistics.fmean(frame_psnr(x, y) for x, y in zip(lifted, teacher_frames, strict=True))
            rows.append((variant, flicker(lifted), err, seconds))
            print(f"{variant}: flicker {rows[-1][1]:.2f}, PSNR {err:.2f} dB, {seconds:.0f} s")
    print(
        f"\nteacher's own flicker at yaw {VIEW_YAW:+.0f}°: {f_teacher:.2f} "
        "(0-255, through the same MP4 encoder)\n"
    )
    print("| lp3d video options | flicker | flicker / teacher's | PSNR vs teacher | run time |")
    print("|---|---:|---:|---:|---:|")
    for variant, f, err, seconds in rows:
        print(f"| `{variant}` | {f:.2f} | {f / f_teacher:.2f}x | {err:.2f} dB | {seconds:.0f} s |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
