"""What the subcommands share: messages, argument types and groups, the model and triplane inputs,
rendering views (raw or super-resolved), and output staging (re-exported from :mod:`lp3d.outputs`).

Errors are :class:`CLIError` (:class:`lp3d.errors.UserError`): one line, exit status 1.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.errors import UsageError, UserError, float_in, int_in, safe_text
from lp3d.outputs import (
    IMAGE_SUFFIXES,
    MESH_SUFFIXES,
    VIDEO_SUFFIXES,
    Staged,
    VideoWriter,
    check_distinct,
    check_folder,
    check_output,
    progress,
    write_image,
)
from lp3d.render.camera import FFHQ_FOCAL, FFHQ_RADIUS
from lp3d.render.native import native_triplane, renderer
from lp3d.render.native import render as native_render
from lp3d.render.settings import RenderSettings, Skips

__all__ = [
    "IMAGE_SUFFIXES",
    "MESH_SUFFIXES",
    "PROG",
    "VIDEO_SUFFIXES",
    "CLIError",
    "Staged",
    "UsageError",
    "UserError",
    "VideoWriter",
    "angle",
    "camera_args",
    "check_distinct",
    "check_folder",
    "check_output",
    "choose_superres",
    "describe_size",
    "final_images",
    "float_in",
    "human_bytes",
    "image_side",
    "int_in",
    "load_triplane_file",
    "make_camera",
    "parse_samples",
    "progress",
    "render_args",
    "render_file_views",
    "native_triplane",
    "render_triplane_file",
    "render_gpu_views",
    "renderer",
    "resize_image",
    "resolve_model",
    "say",
    "superres_model_arg",
    "warn",
    "write_image",
]

PROG = "lp3d"

#: The command line's user-facing error: printed as one line, exit status 1.
CLIError = UserError


def say(message: str) -> None:
    """Progress and results go to stdout; errors and warnings to stderr. Each is one line, with the
    names and file strings in it escaped (:func:`lp3d.errors.safe_text`)."""
    print(safe_text(message), flush=True)


def warn(message: str) -> None:
    print(f"warning: {safe_text(message)}", file=sys.stderr, flush=True)


def human_bytes(n: int) -> str:
    size = float(n)
    for unit in ("B", "KiB", "MiB"):
        if size < 1024:
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{size:.1f} GiB"


def parse_samples(text: str) -> tuple[int, int]:
    """``"48+48"`` -> (48, 48) coarse + fine samples per ray; ``"64"`` -> (64, 0) (no importance pass)."""
    from lp3d.render.settings import MAX_SAMPLES

    parts = text.split("+")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COARSE+FINE such as 48+48, got {text!r}") from None
    if len(values) == 1:
        values.append(0)
    if len(values) != 2:
        raise argparse.ArgumentTypeError(f"expected COARSE+FINE such as 48+48, got {text!r}")
    coarse, fine = values
    if fine and not 4 <= coarse <= MAX_SAMPLES:
        raise argparse.ArgumentTypeError(f"coarse samples must be in [4, {MAX_SAMPLES}] with a fine pass")
    if not 2 <= coarse <= MAX_SAMPLES or not (fine == 0 or 2 <= fine <= MAX_SAMPLES):
        raise argparse.ArgumentTypeError(
            f"samples must be in [2, {MAX_SAMPLES}] (fine may be 0 to skip importance sampling), got {text!r}"
        )
    return coarse, fine


def angle(lo: float | None = None, hi: float | None = None) -> Callable[[str], float]:
    """An angle in degrees: finite (``inf`` and ``nan`` parse as floats but are no direction), and
    within the open interval ``(lo, hi)`` when given."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number of degrees, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number of degrees, got {text}")
        if (lo is not None and value <= lo) or (hi is not None and value >= hi):
            raise argparse.ArgumentTypeError(f"must be in ({lo:g}, {hi:g}) degrees, got {text}")
        return value

    return parse


def image_side(text: str) -> int:
    from lp3d.render.settings import MAX_RESOLUTION

    return int_in(8, MAX_RESOLUTION)(text)


def camera_args(p: argparse.ArgumentParser, *, yaw: float | None = 0.0, pitch: float = 0.0) -> None:
    if yaw is not None:
        p.add_argument(
            "--yaw",
            type=angle(),
            default=yaw,
            help="camera yaw in degrees, > 0 toward the subject's left (default: %(default)s)",
        )
    p.add_argument(
        "--pitch",
        type=angle(-90.0, 90.0),
        default=pitch,
        help="camera pitch in degrees, in (-90, 90), > 0 above (default: %(default)s)",
    )
    p.add_argument("--roll", type=angle(), default=0.0, help="camera roll in degrees (default: 0)")
    p.add_argument(
        "--radius",
        type=float_in(0.1, 100.0),
        default=FFHQ_RADIUS,
        help="camera distance from the origin (default: EG3D's FFHQ %(default)s)",
    )
    p.add_argument(
        "--focal",
        type=float_in(0.1, 100.0),
        default=FFHQ_FOCAL,
        help="normalised focal length (default: EG3D's FFHQ %(default)s)",
    )


def render_args(p: argparse.ArgumentParser, raw_default: int) -> None:
    p.add_argument(
        "--resolution",
        type=image_side,
        default=None,
        help="pixels per image side (default: the super-resolution network's output size, or "
        f"{raw_default} for a raw render)",
    )
    p.add_argument(
        "--raw",
        action="store_true",
        help="write the raw volume render at --resolution, not the super-resolved image",
    )
    p.add_argument(
        "--samples",
        type=parse_samples,
        default=(48, 48),
        metavar="COARSE+FINE",
        help="samples per ray, EG3D's depth_resolution + depth_resolution_importance "
        "(default: 48+48; 64 alone skips the importance pass)",
    )


def superres_model_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        type=Path,
        default=None,
        help="MODEL.onnx (or CHECKPOINT.pt) whose super-resolution network to apply (default: the shipped "
        "model's, when the triplane has its decoder)",
    )


def flip_average_arg(p: argparse.ArgumentParser, what: str = "each photo") -> None:
    """``--flip-average``: :meth:`lp3d.lift.loaded.LoadedEncoder.encode`'s flip-averaged encoding."""
    p.add_argument(
        "--flip-average",
        action="store_true",
        help=f"also encode {what} flipped left to right and average the two heads (the second "
        "mirrored back): slightly closer novel views on held-out heads for twice the encoder's time "
        "(measured in docs/performance.md)",
    )


def resolve_model(arg: Path | None) -> Path:
    from lp3d.lift.inference import DEFAULT_MODEL

    path = arg if arg is not None else DEFAULT_MODEL
    if not path.exists():
        if arg is None:
            raise CLIError(
                f"no model given and the default model {path} does not exist yet; pass --model "
                "MODEL.onnx (with its MODEL.json) or CHECKPOINT.pt, or train one with python -m lp3d.train"
            )
        raise CLIError(f"--model {path}: no such file")
    return path


def load_triplane_file(path: Path) -> Any:
    """A validated :class:`~lp3d.render.triplane.TriplaneData` from ``path`` with one-line errors."""
    from lp3d.render.triplane_io import load_triplane

    # The reader checks the file type first (a FIFO or device is an OSError at once, not a hang or
    # "empty file"), then every size before allocating; both kinds of error name the file.
    try:
        return load_triplane(path)  # TriplaneFileError (ValueError) names the file and key
    except FileNotFoundError:
        raise CLIError(f"{path}: no such file") from None


def render_triplane_file(path: Path) -> Any:
    """``(TriplaneData, lp3d_render.Triplane)`` of a file: validated in Python first (clear errors), then
    loaded by the renderer itself, which keeps everything it uses (such as a baked occupancy grid)."""
    tri = load_triplane_file(path)
    return tri, renderer().Triplane.load(str(path))


def make_camera(
    args: argparse.Namespace, *, yaw: float | None = None, pitch: float | None = None
) -> np.ndarray:
    """A (25,) camera label from the camera arguments (yaw/pitch overridable)."""
    from lp3d.render.camera import look_at_camera

    return look_at_camera(
        yaw_deg=args.yaw if yaw is None else yaw,
        pitch_deg=args.pitch if pitch is None else pitch,
        roll_deg=args.roll,
        radius=args.radius,
        focal=args.focal,
    )


def render_gpu_views(
    tri: Any,
    cameras: np.ndarray,
    args: argparse.Namespace,
    outputs: Sequence[str] = ("rgb",),
    *,
    resolution: int | None = None,
) -> dict[str, np.ndarray]:
    """Render (B, 25) cameras on the GPU at ``resolution`` (default ``args.resolution``) with the
    skips ``args.skips`` (default none: exact); every output has a leading B axis."""
    coarse, fine = args.samples
    settings = RenderSettings(
        resolution=resolution or args.resolution,
        depth_resolution=coarse,
        depth_resolution_importance=fine,
        skips=getattr(args, "skips", None) or Skips(),
    )
    return native_render(tri, np.atleast_2d(cameras), settings, outputs=outputs)


def render_file_views(
    path: Path,
    tri: Any,
    cameras: np.ndarray,
    args: argparse.Namespace,
    outputs: Sequence[str] = ("rgb",),
    *,
    resolution: int | None = None,
) -> dict[str, np.ndarray]:
    """:func:`render_gpu_views` of the triplane read from ``path``; the renderer's checks of its contents
    (such as values that overflow float32 in the decoder) become errors naming the file."""
    try:
        return render_gpu_views(tri, cameras, args, outputs, resolution=resolution)
    except ValueError as e:
        raise CLIError(f"{path}: {e}") from None


def resize_image(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W, 3) or (H, W) uint8 resized to ``size``² (Lanczos; unchanged when already that size)."""
    if image.shape[0] == size and image.shape[1] == size:
        return image
    from PIL import Image

    return np.asarray(Image.fromarray(image).resize((size, size), Image.Resampling.LANCZOS))


def final_images(
    tri: Any,
    cameras: np.ndarray,
    args: argparse.Namespace,
    sr: Any,
    size: int,
    *,
    path: Path | None = None,
    extra: Sequence[str] = (),
) -> tuple[list[np.ndarray], dict[str, np.ndarray]]:
    """The images (size, size, 3) uint8 of (B, 25) cameras: the super-resolved image when ``sr`` (a
    :class:`lp3d.lift.inference.LoadedSuperres`) is given, else the raw render at ``size``. Also returns the
    raw render's outputs, ``extra`` ones included (e.g. depth, at the raw render's resolution)."""
    from lp3d.images import rgb_to_uint8

    resolution = sr.input_resolution if sr is not None else size
    outputs = ["features" if sr is not None else "rgb", *extra]
    if path is not None:
        out = render_file_views(path, tri, cameras, args, outputs, resolution=resolution)
    else:
        out = render_gpu_views(tri, cameras, args, outputs, resolution=resolution)
    rgb = sr(out["features"]) if sr is not None else out["rgb"]
    return [resize_image(rgb_to_uint8(x), size) for x in rgb], out


def choose_superres(args: argparse.Namespace, tri: Any) -> tuple[Any, str]:
    """``(LoadedSuperres or None, a phrase for the output line)`` for rendering the triplane ``tri`` (a
    TriplaneData) in ``render``/``orbit``: the rules in :mod:`lp3d.cli`'s docstring."""
    from lp3d.lift.inference import DEFAULT_MODEL, load_superres

    if args.raw:
        return None, "raw volume render (--raw)"
    if args.model is not None:
        model = resolve_model(args.model)
        sr = load_superres(model)
        if sr is None:
            raise CLIError(
                f"--model {model}: the package has no super-resolution network; drop --model (or pass --raw)"
            )
        if not sr.accepts(tri):
            raise CLIError(
                f"{args.triplane}: its decoder or scene bounds are not those of --model {model}, whose "
                "super-resolution network reads that decoder's features; pass --raw (or the triplane's model)"
            )
        return sr, f"super-resolved by {sr.description}"
    if not DEFAULT_MODEL.exists():
        return None, "raw volume render (no model: the shipped model is not installed)"
    sr = load_superres(DEFAULT_MODEL)
    if sr is None:
        return None, "raw volume render (the shipped model has no super-resolution network)"
    if not sr.accepts(tri):
        return None, (
            "raw volume render (no super-resolution: the triplane's decoder is not the shipped model's; "
            "--model MODEL applies another package's)"
        )
    return sr, f"super-resolved by the shipped model's {sr.description}"


def describe_size(sr: Any, size: int) -> str:
    """``64² raw -> 256²`` (and the resize, when ``size`` is not the network's output)."""
    if sr is None:
        return f"{size}²"
    text = f"{sr.input_resolution}² raw -> {sr.output_resolution}²"
    return text if size == sr.output_resolution else f"{text}, resized to {size}²"
