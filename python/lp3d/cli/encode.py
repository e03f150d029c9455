"""``lp3d encode``: photo(s) -> triplane file(s): read, detect the face, level and crop it, encode."""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.cli.common import (
    CLIError,
    Staged,
    check_distinct,
    check_folder,
    check_output,
    flip_average_arg,
    int_in,
    resolve_model,
    say,
    warn,
    write_image,
)
from lp3d.cli.refining import add_refine_argument, refine_triplanes
from lp3d.errors import safe_text

HELP = "photo(s) -> triplane .npz (detect, align, crop, encode)"
DESCRIPTION = (
    "Encode portrait photos into triplane files. Each photo is read, the "
    "largest face and its five landmarks are found (dlib, offline), its camera is estimated from them "
    "and it is cropped to the training framing, then encoded; --refine fits the head to the photo at "
    "that camera."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "inputs", nargs="+", type=Path, metavar="PHOTO", help="image files and/or folders of images"
    )
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="a .npz file (one photo) or a folder (several photos: FOLDER/<name>.npz)",
    )
    p.add_argument(
        "--model",
        type=Path,
        default=None,
        help="MODEL.onnx (with MODEL.json beside it) or CHECKPOINT.pt (default: the shipped "
        "lp3d/lift/models/small.onnx in the package)",
    )
    p.add_argument(
        "--backend",
        choices=("onnx", "torch"),
        default=None,
        help="onnx (onnxruntime) or torch (default: by the model file's suffix)",
    )
    p.add_argument(
        "--no-detect",
        action="store_true",
        help="skip face detection: the photo is already a centred portrait (centre square crop)",
    )
    p.add_argument(
        "--batch-size", type=int_in(1, 256), default=4, help="images per encoder call (default: 4)"
    )
    flip_average_arg(p)
    add_refine_argument(p)
    p.add_argument("--half", action="store_true", help="store the planes as float16 (half the file size)")
    p.add_argument(
        "--save-crop", action="store_true", help="also write the aligned input crop as <name>.crop.png"
    )


def collect_images(inputs: Sequence[Path]) -> list[Path]:
    """Files as given; folders expand to their images (non-recursive, sorted)."""
    from lp3d.photo import PHOTO_SUFFIXES

    found: list[Path] = []
    for item in inputs:
        if item.is_dir():
            images = sorted(p for p in item.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
            if not images:
                raise CLIError(f"{item}: folder holds no images ({', '.join(PHOTO_SUFFIXES)})")
            found += images
        elif not item.exists():
            raise CLIError(f"{item}: no such file or folder")
        else:
            found.append(item)
    return found


def _plan_outputs(images: Sequence[Path], output: Path) -> tuple[list[Path], Path | None]:
    """Destination per image, and the folder to create (if any). One image and a ``.npz`` name: that
    file; otherwise ``output`` is a folder (created if missing) holding ``<stem>.npz`` per image."""
    if output.suffix.lower() == ".npz" and not output.is_dir():
        if len(images) != 1:
            raise CLIError(f"-o {output}: {len(images)} images need an output folder, not one .npz file")
        check_output(output, (".npz",))
        return [output], None
    if output.exists() and not output.is_dir():
        raise CLIError(f"-o {output}: exists and is not a folder (name a .npz file for a single image)")
    if output.suffix and not output.exists():
        raise CLIError(f"-o {output}: unsupported format {output.suffix}; name a .npz file or a folder")
    check_folder(output.parent if not output.exists() else output, "output folder", output)
    stems: dict[str, Path] = {}
    for img in images:
        if img.stem in stems:
            raise CLIError(f"{img} and {stems[img.stem]} would both write {output / (img.stem + '.npz')}")
        stems[img.stem] = img
    return [output / f"{img.stem}.npz" for img in images], (None if output.exists() else output)


def _crop_path(dest: Path) -> Path:
    """Where ``lp3d encode --save-crop`` writes the aligned crop of the photo encoded to ``dest``."""
    return dest.with_name(dest.stem + ".crop.png")


def _encode(encoder: Any, crops: Sequence[np.ndarray], batch_size: int, flip_average: bool) -> np.ndarray:
    """The crops' planes (N, 3, 32, T, T), ``batch_size`` images per encoder call."""
    from lp3d.photo import to_encoder_input

    batch = to_encoder_input(np.stack(crops))
    return np.concatenate(
        [
            encoder.encode(batch[i : i + batch_size], flip_average=flip_average)
            for i in range(0, len(batch), batch_size)
        ]
    )


def _prepare_all(
    images: Sequence[Path], size: int, *, detect: bool
) -> tuple[list[np.ndarray], list[tuple[float, float] | None]]:
    """Each photo read, its face found and cropped (:func:`lp3d.photo.prepare_photo`), with its pose;
    one CLIError listing every photo that cannot be used."""
    from lp3d.photo import PhotoError, load_image, prepare_photo

    crops: list[np.ndarray] = []
    poses: list[tuple[float, float] | None] = []
    failures: list[str] = []
    for img in images:
        try:
            rgb, notes = load_image(img)
            for note in notes:
                warn(note)
            prep = prepare_photo(rgb, size, detect=detect, name=str(img))
        except PhotoError as e:
            failures.append(str(e))
            continue
        crops.append(prep.image)
        poses.append(prep.pose)
        say(f"{img}: {prep.description}")
    if failures:
        if len(failures) == 1:
            raise CLIError(failures[0])
        raise CLIError(f"{len(failures)} of {len(images)} photos cannot be used:\n  " + "\n  ".join(failures))
    return crops, poses


def run(args: argparse.Namespace) -> int:
    from lp3d.lift.inference import load_encoder
    from lp3d.render.triplane_io import save_triplane

    images = collect_images(args.inputs)
    destinations, new_folder = _plan_outputs(images, args.output)
    crop_paths = [_crop_path(dest) for dest in destinations] if args.save_crop else []
    check_distinct(
        [("photo", img) for img in images],
        [("output", dest) for dest in destinations] + [("crop", crop) for crop in crop_paths],
    )
    model_path = resolve_model(args.model)

    t0 = time.perf_counter()
    encoder = load_encoder(model_path, args.backend)
    pkg = encoder.package
    say(
        f"model: {encoder.description}, config {pkg.config_name!r}, {pkg.image_size}² -> "
        f"{pkg.triplane_resolution}² triplane, loaded in {time.perf_counter() - t0:.2f} s"
    )

    # Read, detect and crop everything first: one bad photo fails the run before anything is written.
    t0 = time.perf_counter()
    crops, poses = _prepare_all(images, pkg.image_size, detect=not args.no_detect)
    t_prep = time.perf_counter() - t0

    t0 = time.perf_counter()
    planes = _encode(encoder, crops, args.batch_size, args.flip_average)
    t_enc = time.perf_counter() - t0
    how = ", flip-averaged" if args.flip_average else ""
    model = f"model {pkg.config_name}, {encoder.backend}{how}"
    tris = [
        pkg.triplane(plane, source=safe_text(f"lp3d encode {img.name} ({model})"))
        for img, plane in zip(images, planes, strict=True)
    ]
    t0 = time.perf_counter()
    if args.refine > 0:
        tris = refine_triplanes(tris, crops, args.refine, [str(img) for img in images], poses, pkg)
    t_refine = time.perf_counter() - t0

    t0 = time.perf_counter()
    with Staged() as staged:
        if new_folder is not None:
            staged.mkdir(new_folder)
        for dest, tri, crop in zip(destinations, tris, crops, strict=True):
            if args.half:
                tri = dataclasses.replace(tri, planes=tri.planes.astype(np.float16))
            save_triplane(staged.temp(dest), tri)
            if args.save_crop:
                write_image(staged.temp(_crop_path(dest)), crop, ".png")
        written = staged.commit()
    t_write = time.perf_counter() - t0
    n = len(images)
    say(
        f"timings: detect+crop {t_prep:.2f} s ({t_prep / n:.3f} s/image), encode {t_enc:.2f} s "
        f"({t_enc / n:.3f} s/image, {encoder.backend}{how}), "
        + (f"refine {t_refine:.2f} s ({t_refine / n:.2f} s/image), " if args.refine else "")
        + f"write {t_write:.2f} s"
    )
    for path in written:
        say(f"wrote {path}")
    return 0
