"""``lp3d demo``: photo in, 3D out, with the shipped model.

Two portraits are lifted to triplanes by the encoder (onnxruntime) and rendered by ``lp3d_render``:

* **a teacher portrait**: a held-out identity of the built-in procedural teacher (a seed the model
  never trained on), rendered frontally at the encoder's input size, the framing it was trained on.
  Its own triplane is rendered beside the student's, so the two can be compared view by view;
* **a real photo**: scikit-image's astronaut (Eileen Collins, NASA, public domain), with the face
  detected and cropped exactly as ``lp3d encode`` does. The shipped model was distilled from the
  *procedural* teacher, so it lifts stylised heads; on a real photo it shows how far that domain
  reaches (a model distilled from EG3D is what lifts real portraits; see the README).

Outputs (in ``--out``, written atomically): ``<name>.npz`` triplanes, ``<name>.html`` web pages of
them (``lp3d share``: open one in a WebGPU browser to turn the head), ``<name>.crop.png`` encoder
inputs, ``side_by_side.png`` (input | views from yaw -35° to 35°; the teacher's own views under its
row) and ``orbit.gif`` (both heads turning). ``--refine N`` fits each lifted head to its portrait
(:mod:`lp3d.lift.refine`) and adds ``<name>.refined.npz``, a row of refined views under each head's
row, and the refined heads to the orbit. When the model package has a super-resolution network,
the lifted heads' views are its images (at its output size unless ``--resolution`` says otherwise);
``--raw`` shows the plain volume renders. The teacher's own views are always its volume renders.

    lp3d demo --out demo_out
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.cli.common import (
    Staged,
    VideoWriter,
    describe_size,
    final_images,
    flip_average_arg,
    image_side,
    int_in,
    native_triplane,
    parse_samples,
    progress,
    renderer,
    resolve_model,
)
from lp3d.cli.refining import add_refine_argument, refine_triplanes
from lp3d.outputs import check_output_folder
from lp3d.photo import prepare_photo
from lp3d.render.camera import orbit_angles

HELP = "photo in, 3D out: lift a teacher portrait and a real photo with the shipped model"
DESCRIPTION = (
    "Encode a built-in teacher portrait and scikit-image's astronaut with the shipped model; write their "
    "triplanes, web pages that render them in a browser, a side-by-side PNG and an orbit GIF."
)

#: The teacher portrait: the first held-out evaluation identity (``TrainConfig.eval_seed_start``).
TEACHER_SEED = 1_000_000
#: The procedural teacher version the shipped ``small`` model was distilled from: it is shown a head of
#: the teacher it learnt (v2).
SHIPPED_TEACHER_VERSION = 2
#: Yaws of the side-by-side views, degrees.
VIEW_YAWS = (-35.0, -15.0, 0.0, 15.0, 35.0)
#: Orbit frames per render call (a batch keeps the progress bar moving and the memory small).
ORBIT_BATCH = 6


@dataclass
class Portrait:
    """One demo input: its name, the encoder input crop (S, S, 3) uint8, how it was made, and (for the
    teacher portrait) the teacher's own triplane."""

    name: str
    crop: np.ndarray
    description: str
    truth: Any = None  # lp3d.render.triplane.TriplaneData
    #: (yaw, pitch) of the portrait's camera: known for the teacher's, found from the face for a photo.
    pose: tuple[float, float] | None = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The demo's options (``lp3d demo``)."""
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: %(default)s)")
    p.add_argument(
        "--model",
        type=Path,
        default=None,
        help="MODEL.onnx (with MODEL.json) or a training CHECKPOINT.pt (default: the shipped model)",
    )
    p.add_argument(
        "--resolution",
        type=image_side,
        default=None,
        help="pixels per image side (default: the super-resolution network's output size, else 128)",
    )
    p.add_argument(
        "--raw", action="store_true", help="show raw volume renders, not the super-resolved images"
    )
    p.add_argument(
        "--samples",
        type=parse_samples,
        default=(24, 24),
        help="coarse+fine samples per ray, e.g. 48+48 (default: 24+24, quick on a CPU)",
    )
    p.add_argument("--frames", type=int_in(2, 720), default=24, help="orbit frames (default: 24)")
    flip_average_arg(p, "each portrait")
    add_refine_argument(p, "its portrait")


def teacher_portrait(size: int, samples: tuple[int, int]) -> Portrait:
    """The procedural teacher's held-out identity, rendered frontally at ``size``² by lp3d_render."""
    import lp3d_render
    from lp3d.images import rgb_to_uint8
    from lp3d.render.camera import look_at_camera
    from lp3d.teachers.procedural import ProceduralTeacher

    truth = ProceduralTeacher(version=SHIPPED_TEACHER_VERSION).sample(TEACHER_SEED)
    out = lp3d_render.render(
        native_triplane(truth),
        look_at_camera(),
        resolution=size,
        depth_resolution=samples[0],
        depth_resolution_importance=samples[1],
        outputs=["rgb"],
    )
    crop = rgb_to_uint8(out["rgb"])
    return Portrait(
        "teacher_portrait", crop, f"procedural teacher, held-out seed {TEACHER_SEED}", truth, (0.0, 0.0)
    )


def astronaut_portrait(size: int) -> Portrait:
    """scikit-image's astronaut, face found, aligned and cropped as ``lp3d encode`` does."""
    from skimage import data

    prep = prepare_photo(data.astronaut(), size, detect=True, name="skimage astronaut")
    return Portrait("astronaut", prep.image, f"scikit-image astronaut: {prep.description}", pose=prep.pose)


def _views(tri: Any, cams: np.ndarray, resolution: int, samples: tuple[int, int]) -> list[np.ndarray]:
    """RGB (R, R, 3) uint8 of an ``lp3d_render.Triplane`` from cameras (B, 25), in one batched render."""
    import lp3d_render
    from lp3d.images import rgb_to_uint8

    out = lp3d_render.render(
        tri,
        cams,
        resolution=resolution,
        depth_resolution=samples[0],
        depth_resolution_importance=samples[1],
        outputs=["rgb"],
    )
    return [rgb_to_uint8(rgb) for rgb in out["rgb"]]


def _fit(image: np.ndarray, size: int) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.fromarray(image).resize((size, size), Image.Resampling.BICUBIC))


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with a caption strip above it (PIL's built-in font, no font files needed)."""
    from PIL import Image, ImageDraw

    h, w = image.shape[:2]
    canvas = Image.new("RGB", (w, h + 14), (255, 255, 255))
    canvas.paste(Image.fromarray(image), (0, 14))
    ImageDraw.Draw(canvas).text((3, 1), text, fill=(0, 0, 0))
    return np.asarray(canvas)


def _side_by_side(
    portraits: list[Portrait],
    native: list[Any],
    args: argparse.Namespace,
    sr: Any,
    r: int,
    refined: list[Any] | None = None,
) -> np.ndarray:
    """The contact sheet: input | lp3d's views of each portrait, its ``refined`` views (``--refine``)
    under them, and the teacher's own views under the teacher portrait's rows."""
    from lp3d.images import tile
    from lp3d.render.camera import look_at_camera

    samples = args.samples
    cams = np.stack([look_at_camera(yaw_deg=y) for y in VIEW_YAWS])
    t0 = time.perf_counter()
    rows: list[np.ndarray] = []
    for p, tri in zip(portraits, native, strict=True):
        views = final_images(tri, cams, args, sr, r)[0]
        rows += [_label(_fit(p.crop, r), "input")]
        rows += [_label(v, f"lp3d {y:+.0f}°") for v, y in zip(views, VIEW_YAWS, strict=True)]
        if refined is not None:
            views = final_images(refined[portraits.index(p)], cams, args, sr, r)[0]
            rows += [_label(np.full((r, r, 3), 255, np.uint8), f"refined ({args.refine} steps)")]
            rows += [_label(v, f"refined {y:+.0f}°") for v, y in zip(views, VIEW_YAWS, strict=True)]
        if p.truth is not None:
            rows += [_label(np.full((r, r, 3), 255, np.uint8), "teacher's own")]
            truth = _views(native_triplane(p.truth), cams, r, samples)
            rows += [_label(v, f"teacher {y:+.0f}°") for v, y in zip(truth, VIEW_YAWS, strict=True)]
    sheet = tile(rows, columns=1 + len(VIEW_YAWS))
    print(
        f"rendered the views in {time.perf_counter() - t0:.1f} s ({describe_size(sr, r)}, "
        f"{samples[0]}+{samples[1]} samples)"
    )
    return sheet


def _write_orbit(path: Path, heads: list[Any], args: argparse.Namespace, sr: Any, r: int) -> None:
    """``orbit.gif``: the heads side by side, turning through yaw ±35° and pitch ±10°."""
    from lp3d.render.camera import look_at_camera

    writer = VideoWriter(path, ".gif", fps=12)
    bar = progress(args.frames, "orbit")
    orbit = np.stack(
        [look_at_camera(yaw_deg=y, pitch_deg=p) for y, p in orbit_angles(args.frames, 35.0, 10.0)]
    )
    try:
        for i in range(0, len(orbit), ORBIT_BATCH):
            batch = orbit[i : i + ORBIT_BATCH]
            frames = [final_images(tri, batch, args, sr, r)[0] for tri in heads]
            for frame in zip(*frames, strict=True):
                writer.add(np.concatenate(frame, axis=1))  # the heads side by side
            bar.update(len(frames[0]))
        writer.close()
    finally:
        bar.close()


def run(args: argparse.Namespace) -> int:
    """The demo; raises :class:`lp3d.errors.UserError` (or a ValueError) with a clear message."""
    from lp3d.images import save_png
    from lp3d.lift.inference import load_encoder
    from lp3d.photo import to_encoder_input
    from lp3d.render.triplane_io import save_triplane
    from lp3d.share import write_page

    check_output_folder(args.out)

    model = resolve_model(args.model)
    t0 = time.perf_counter()
    encoder = load_encoder(model, superres=not args.raw)
    pkg, sr = encoder.package, encoder.superres
    info = renderer().adapter_info()
    print(f"renderer: {info['name']} ({info['backend']}, {info['device_type']})")
    print(
        f"model: {encoder.description}, config {pkg.config_name!r}, {pkg.image_size}² -> "
        f"{pkg.triplane_resolution}² triplane, loaded in {time.perf_counter() - t0:.2f} s"
    )
    r, samples = args.resolution or (sr.output_resolution if sr is not None else 128), args.samples
    if args.raw:
        how = "raw volume renders (--raw)"
    elif sr is not None:
        how = f"super-resolved by {sr.description}"
    else:
        how = "raw volume renders (the model has no super-resolution network)"
    print(f"views: {describe_size(sr, r)}; {how}")
    print("preparing the inputs")
    portraits = [teacher_portrait(pkg.image_size, samples), astronaut_portrait(pkg.image_size)]
    for p in portraits:
        print(f"  {p.name}: {p.description}")

    t0 = time.perf_counter()
    inputs = to_encoder_input(np.stack([p.crop for p in portraits]))
    planes = encoder.encode(inputs, flip_average=args.flip_average)
    ms = (time.perf_counter() - t0) * 1e3 / len(portraits)
    how = ", flip-averaged" if args.flip_average else ""
    print(f"encoded {len(portraits)} portraits: {ms:.0f} ms per image ({encoder.backend}{how})")
    lifted = [
        pkg.triplane(plane, source=f"lp3d demo: {p.description} (model {pkg.config_name}{how})")
        for p, plane in zip(portraits, planes, strict=True)
    ]

    native = [native_triplane(tri) for tri in lifted]  # uploaded once, rendered many times
    refined: list[Any] = []
    if args.refine > 0:
        refined = refine_triplanes(
            lifted,
            [p.crop for p in portraits],
            args.refine,
            [p.name for p in portraits],
            [p.pose for p in portraits],
            pkg,
        )
    native_refined = [native_triplane(tri) for tri in refined]
    sheet = _side_by_side(portraits, native, args, sr, r, native_refined or None)

    args.out.mkdir(parents=True, exist_ok=True)
    with Staged() as staged:
        for p, tri in zip(portraits, lifted, strict=True):
            save_triplane(staged.temp(args.out / f"{p.name}.npz"), tri)
            write_page(staged.temp(args.out / f"{p.name}.html"), tri, title=f"lp3d demo: {p.description}")
            save_png(staged.temp(args.out / f"{p.name}.crop.png"), p.crop)
        for p, tri in zip(portraits, refined, strict=False):
            save_triplane(staged.temp(args.out / f"{p.name}.refined.npz"), tri)
        save_png(staged.temp(args.out / "side_by_side.png"), sheet)
        gif = args.out / "orbit.gif"
        _write_orbit(staged.temp(gif), native_refined or native, args, sr, r)
        written = staged.commit()
    for path in written:
        print(f"wrote {path}")
    print(
        f"open {args.out / 'side_by_side.png'} and {gif}; look around with: lp3d-view {written[0]}, "
        f"or open {written[1]} in a WebGPU browser"
    )
    return 0
