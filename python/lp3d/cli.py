"""``lp3d``: the command line. One entry point, one subcommand per job::

    lp3d encode photo.jpg -o head.npz            photo(s) -> triplane(s) (face detection + alignment)
    lp3d render head.npz --yaw 30 -o view.png    one view (also --depth, --features-channel)
    lp3d orbit head.npz -o orbit.mp4             a turntable video (.gif or .mp4)
    lp3d mesh head.npz -o head.glb               marching cubes (.ply, .obj or .glb)
    lp3d info head.npz                           what is in a triplane file
    lp3d video in.mp4 -o out.mp4 --yaw 20        lift a talking-head video frame by frame
    lp3d demo                                    the end-to-end demo

**Super-resolution.** When the model package has a super-resolution network (SR; see
``docs/model-package.md``), ``render``, ``orbit``, ``video`` and ``demo`` draw the raw feature image at
the network's input size and write the super-resolved image at its output size (``--resolution``
resizes that); ``--raw`` gives the plain volume render instead. ``video`` and ``demo`` use their
``--model``'s SR. A triplane file names no model, so ``render`` and ``orbit`` apply the SR of
``--model MODEL`` when given (an error if that package has none, or if the triplane's decoder and
bounds are not that package's), else the shipped model's SR when the triplane has the shipped model's
decoder and bounds (every triplane the shipped model encodes has), else none (raw, and they say why).

Every subcommand has ``--help``. Errors go to stderr as ``lp3d <command>: error: <what and where>``,
with exit status 1 (2 for a usage error); set ``LP3D_DEBUG=1`` for the traceback. Outputs are written
to temporary files beside their destination and renamed into place only when everything succeeded,
so a failed command leaves no partial files; an output that would replace an input or another output
(by name, relative path or link) is refused before any work. Rendering uses ``lp3d_render`` (wgpu);
on a machine without a GPU set ``VK_DRIVER_FILES`` to Mesa's lavapipe ICD (see README).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lp3d.atomic import StagedFiles
from lp3d.camera import FFHQ_FOCAL, FFHQ_RADIUS

if TYPE_CHECKING:
    from lp3d.triplane import TriplaneData

PROG = "lp3d"

#: Output formats per kind of output.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".gif")
MESH_SUFFIXES = (".ply", ".obj", ".glb")
#: Crop smoothing in ``lp3d video`` (exponential, per frame): damps the Haar box's frame-to-frame jitter.
VIDEO_CROP_SMOOTHING = 0.6


class CLIError(Exception):
    """A user-facing error: printed as one line, exit status 1."""


# ============================================================================================ helpers


def _say(message: str) -> None:
    """Progress and results go to stdout; errors and warnings to stderr."""
    print(message, flush=True)


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr, flush=True)


def _human_bytes(n: int) -> str:
    size = float(n)
    for unit in ("B", "KiB", "MiB"):
        if size < 1024:
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{size:.1f} GiB"


class Staged(StagedFiles):
    """The CLI's outputs: :class:`lp3d.atomic.StagedFiles` (temporary files beside their
    destinations, published together by :meth:`commit`, all deleted on failure) whose write errors
    are one-line :class:`CLIError` messages naming the destination, never a temporary file."""

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        final = self.destination(exc.filename) if isinstance(exc, OSError) else None
        super().__exit__(exc_type, exc, tb)
        if final is not None and isinstance(exc, OSError):
            raise CLIError(f"cannot write {final}: {exc.strerror or exc}") from exc

    def temp(self, final: str | os.PathLike[str]) -> Path:
        try:
            return super().temp(final)
        except OSError as e:
            raise CLIError(f"cannot write {final}: {e.strerror or e}") from None

    def commit(self) -> list[Path]:
        try:
            return super().commit()
        except OSError as e:
            failed = self.destination(e.filename) or self.destinations[-1]
            self.discard()
            raise CLIError(f"cannot write {failed}: {e.strerror or e}") from None


def check_output(path: Path, suffixes: Sequence[str], what: str = "output") -> Path:
    """Fail early (before any slow work) if ``path`` cannot be written as one of ``suffixes``."""
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        raise CLIError(
            f"{what} {path}: unsupported format {suffix or '(no suffix)'}; use one of {', '.join(suffixes)}"
        )
    if path.is_dir():
        raise CLIError(f"{what} {path} is a folder; give a file name")
    _check_folder(path.parent, what, path)
    return path


def _file_key(path: Path) -> tuple[object, ...]:
    """What identifies the file ``path`` names: its device and inode when it exists (so symlinks, hard
    links and relative paths to one file agree), else its fully resolved path."""
    try:
        st = path.stat()
    except OSError:
        try:
            return ("path", str(path.resolve()))
        except (OSError, RuntimeError):  # a symlink loop
            return ("path", os.path.abspath(path))
    return ("inode", st.st_dev, st.st_ino)


def check_distinct(inputs: Sequence[tuple[str, Path]], outputs: Sequence[tuple[str, Path]]) -> None:
    """Fail early (before any slow work) if an output would replace an input or another output.

    ``inputs`` and ``outputs`` are ``(what, path)`` pairs, ``what`` naming the argument for the
    message. Every command that reads files and writes others calls this once with all of them."""
    seen: dict[tuple[object, ...], tuple[str, Path, bool]] = {}
    for what, path in inputs:
        seen.setdefault(_file_key(path), (what, path, True))
    for what, path in outputs:
        key = _file_key(path)
        if key in seen:
            other_what, other, is_input = seen[key]
            if is_input:
                raise CLIError(
                    f"{what} {path} is the same file as the {other_what} {other}: writing it would "
                    "destroy the input; choose another output name"
                )
            raise CLIError(f"{what} {path} and {other_what} {other} name the same file")
        seen[key] = (what, path, False)


def _check_folder(folder: Path, what: str, path: Path) -> None:
    if not folder.exists():
        raise CLIError(f"{what} {path}: folder {folder} does not exist")
    if not folder.is_dir():
        raise CLIError(f"{what} {path}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CLIError(f"{what} {path}: folder {folder} is not writable")


def load_triplane_file(path: Path) -> Any:
    """A validated :class:`~lp3d.triplane.TriplaneData` from ``path`` with one-line errors."""
    from lp3d.triplane_io import load_triplane

    # The reader checks the file type first (a FIFO or device is an OSError at once, not a hang or
    # "empty file"), then every size before allocating; both kinds of error name the file.
    try:
        return load_triplane(path)  # TriplaneFileError (ValueError) names the file and key
    except FileNotFoundError:
        raise CLIError(f"{path}: no such file") from None


def renderer() -> Any:
    """The ``lp3d_render`` module (imported on first use: it creates the GPU device)."""
    try:
        import lp3d_render
    except ImportError as e:
        raise CLIError(
            f"the renderer lp3d_render is not installed ({e}); build it with ./dev setup"
        ) from None
    return lp3d_render


def render_triplane_file(path: Path) -> Any:
    """``(TriplaneData, lp3d_render.Triplane)`` of a file: validated in Python first (clear errors), then
    loaded by the renderer itself, which keeps everything it uses (such as a baked occupancy grid)."""
    tri = load_triplane_file(path)
    return tri, renderer().Triplane.load(str(path))


def render_triplane(tri: TriplaneData) -> Any:
    """The ``lp3d_render.Triplane`` of a TriplaneData (:meth:`TriplaneData.to_native`), with a CLI
    error naming the fix when the renderer is not installed."""
    renderer()
    return tri.to_native()


def parse_samples(text: str) -> tuple[int, int]:
    """``"48+48"`` -> (48, 48) coarse + fine samples per ray; ``"64"`` -> (64, 0) (no importance pass)."""
    from lp3d.settings import MAX_SAMPLES

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


def _int_in(lo: int, hi: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be in [{lo}, {hi}], got {value}")
        return value

    return parse


def _float_in(lo: float, hi: float, *, hi_open: bool = False) -> Callable[[str], float]:
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(value) and lo <= value and (value < hi if hi_open else value <= hi)):
            raise argparse.ArgumentTypeError(
                f"must be in [{lo:g}, {hi:g}{')' if hi_open else ']'}, got {text}"
            )
        return value

    return parse


def _angle(lo: float | None = None, hi: float | None = None) -> Callable[[str], float]:
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


def _resolution(text: str) -> int:
    from lp3d.settings import MAX_RESOLUTION

    return _int_in(8, MAX_RESOLUTION)(text)


def _camera_args(p: argparse.ArgumentParser, *, yaw: float | None = 0.0, pitch: float = 0.0) -> None:
    if yaw is not None:
        p.add_argument(
            "--yaw",
            type=_angle(),
            default=yaw,
            help="camera yaw in degrees, > 0 toward the subject's left (default: %(default)s)",
        )
    p.add_argument(
        "--pitch",
        type=_angle(-90.0, 90.0),
        default=pitch,
        help="camera pitch in degrees, in (-90, 90), > 0 above (default: %(default)s)",
    )
    p.add_argument("--roll", type=_angle(), default=0.0, help="camera roll in degrees (default: 0)")
    p.add_argument(
        "--radius",
        type=_float_in(0.1, 100.0),
        default=FFHQ_RADIUS,
        help="camera distance from the origin (default: EG3D's FFHQ %(default)s)",
    )
    p.add_argument(
        "--focal",
        type=_float_in(0.1, 100.0),
        default=FFHQ_FOCAL,
        help="normalised focal length (default: EG3D's FFHQ %(default)s)",
    )


def _render_args(p: argparse.ArgumentParser, resolution: int) -> None:
    p.add_argument(
        "--resolution",
        type=_resolution,
        default=None,
        help="pixels per image side (default: the super-resolution network's output size, or "
        f"{resolution} for a raw render)",
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


def _superres_model_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        type=Path,
        default=None,
        help="MODEL.onnx (or CHECKPOINT.pt) whose super-resolution network to apply (default: the shipped "
        "model's, when the triplane has its decoder)",
    )


def make_camera(
    args: argparse.Namespace, *, yaw: float | None = None, pitch: float | None = None
) -> np.ndarray:
    """A (25,) camera label from the camera arguments (yaw/pitch overridable)."""
    from lp3d.camera import look_at_camera

    return look_at_camera(
        yaw_deg=args.yaw if yaw is None else yaw,
        pitch_deg=args.pitch if pitch is None else pitch,
        roll_deg=args.roll,
        radius=args.radius,
        focal=args.focal,
    )


def render_views(
    tri: Any,
    cameras: np.ndarray,
    args: argparse.Namespace,
    outputs: Sequence[str] = ("rgb",),
    *,
    resolution: int | None = None,
) -> dict[str, np.ndarray]:
    """Render (B, 25) cameras at ``resolution`` (default ``args.resolution``); every output has a
    leading B axis."""
    coarse, fine = args.samples
    out = renderer().render(
        tri,
        np.atleast_2d(cameras),
        resolution=resolution or args.resolution,
        depth_resolution=coarse,
        depth_resolution_importance=fine,
        outputs=list(outputs),
    )
    return dict(out)


def render_file_views(
    path: Path,
    tri: Any,
    cameras: np.ndarray,
    args: argparse.Namespace,
    outputs: Sequence[str] = ("rgb",),
    *,
    resolution: int | None = None,
) -> dict[str, np.ndarray]:
    """:func:`render_views` of the triplane read from ``path``; the renderer's checks of its contents
    (such as values that overflow float32 in the decoder) become errors naming the file."""
    try:
        return render_views(tri, cameras, args, outputs, resolution=resolution)
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
    :class:`lp3d.inference.LoadedSuperres`) is given, else the raw render at ``size``. Also returns the
    raw render's outputs, ``extra`` ones included (e.g. depth, at the raw render's resolution)."""
    from lp3d.images import rgb_to_uint8

    resolution = sr.input_resolution if sr is not None else size
    outputs = ["features" if sr is not None else "rgb", *extra]
    if path is not None:
        out = render_file_views(path, tri, cameras, args, outputs, resolution=resolution)
    else:
        out = render_views(tri, cameras, args, outputs, resolution=resolution)
    rgb = sr(out["features"]) if sr is not None else out["rgb"]
    return [resize_image(rgb_to_uint8(x), size) for x in rgb], out


def choose_superres(args: argparse.Namespace, tri: Any) -> tuple[Any, str]:
    """``(LoadedSuperres or None, a phrase for the output line)`` for rendering the triplane ``tri`` (a
    TriplaneData) in ``render``/``orbit``: the rules in this module's docstring."""
    from lp3d.inference import DEFAULT_MODEL, load_superres

    if args.raw:
        return None, "raw volume render (--raw)"
    if args.model is not None:
        model = _model_path(args.model)
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


def _describe_size(sr: Any, size: int) -> str:
    """``64² raw -> 256²`` (and the resize, when ``size`` is not the network's output)."""
    if sr is None:
        return f"{size}²"
    text = f"{sr.input_resolution}² raw -> {sr.output_resolution}²"
    return text if size == sr.output_resolution else f"{text}, resized to {size}²"


def write_image(path: Path, image: np.ndarray, fmt_suffix: str) -> None:
    """Write (H, W, 3) or (H, W) uint8 as PNG or JPEG (by ``fmt_suffix``)."""
    from PIL import Image

    fmt = "PNG" if fmt_suffix.lower() == ".png" else "JPEG"
    kwargs = {"quality": 95} if fmt == "JPEG" else {}
    Image.fromarray(np.ascontiguousarray(image)).save(path, format=fmt, **kwargs)


class VideoWriter:
    """Frames (H, W, 3) uint8 into a ``.gif`` (imageio/Pillow, written on :meth:`close`) or an ``.mp4``
    (H.264 via the ffmpeg binary bundled with imageio-ffmpeg, streamed)."""

    def __init__(self, path: Path, fmt_suffix: str, fps: float) -> None:
        self.path, self.fps, self.suffix = path, fps, fmt_suffix.lower()
        self.frames: list[np.ndarray] = []
        self._mp4: Any = None
        self.count = 0

    def add(self, frame: np.ndarray) -> None:
        frame = np.ascontiguousarray(frame, dtype=np.uint8)
        if self.suffix == ".gif":
            self.frames.append(frame)
        else:
            if self._mp4 is None:
                self._mp4 = self._open_mp4(frame.shape[1], frame.shape[0])
            self._mp4.send(frame.tobytes())
        self.count += 1

    def _open_mp4(self, width: int, height: int) -> Any:
        try:
            import imageio_ffmpeg

            imageio_ffmpeg.get_ffmpeg_exe()
        except (ImportError, RuntimeError) as e:
            raise CLIError(f"MP4 output needs imageio-ffmpeg (pip install imageio-ffmpeg): {e}") from None
        gen = imageio_ffmpeg.write_frames(
            str(self.path),
            (width, height),
            fps=self.fps,
            codec="libx264",
            quality=8,
            macro_block_size=2,  # yuv420p needs even sides; 16 would rescale most sizes
            ffmpeg_log_level="error",
        )
        gen.send(None)  # start ffmpeg
        return gen

    def close(self) -> None:
        if self.suffix == ".gif":
            if not self.frames:
                raise CLIError("no frames to write")
            import imageio.v3 as iio

            iio.imwrite(
                self.path, np.stack(self.frames), extension=".gif", duration=1000.0 / self.fps, loop=0
            )
        elif self._mp4 is not None:
            gen, self._mp4 = self._mp4, None
            gen.close()
        elif self.count == 0:
            raise CLIError("no frames to write")

    def abort(self) -> None:
        if self._mp4 is not None:
            with contextlib.suppress(Exception):
                self._mp4.close()
            self._mp4 = None


def progress(total: int | None, desc: str) -> Any:
    """A tqdm progress bar on stderr (a no-op object when tqdm is missing)."""
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency

        class _Null:
            def update(self, n: int = 1) -> None: ...
            def close(self) -> None: ...
            def set_postfix_str(self, s: str) -> None: ...

        return _Null()
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=True)


# ============================================================================================ render


def cmd_render(args: argparse.Namespace) -> int:
    out_path = check_output(args.output, IMAGE_SUFFIXES)
    depth_path = check_output(args.depth, IMAGE_SUFFIXES, "--depth") if args.depth else None
    outputs = [("-o", out_path)] + ([("--depth", depth_path)] if depth_path is not None else [])
    check_distinct([("triplane", args.triplane)], outputs)
    tri, rtri = render_triplane_file(args.triplane)
    from lp3d.images import depth_to_uint8

    camera = make_camera(args)[None]
    extra = ["depth", "weights_sum"] if depth_path is not None else []
    start = time.perf_counter()
    if args.features_channel is not None:
        # A feature channel is a raw quantity: never super-resolved.
        sr, how = None, "raw volume render"
        size = args.resolution or 256
        out = render_file_views(args.triplane, rtri, camera, args, ["features", *extra], resolution=size)
        channel = out["features"][0, args.features_channel]
        image = np.round((np.clip(channel, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    else:
        sr, how = choose_superres(args, tri)
        size = args.resolution or (sr.output_resolution if sr is not None else 256)
        images, out = final_images(rtri, camera, args, sr, size, path=args.triplane, extra=extra)
        image = images[0]
    seconds = time.perf_counter() - start
    with Staged() as staged:
        write_image(staged.temp(out_path), image, out_path.suffix)
        if depth_path is not None:
            depth = depth_to_uint8(out["depth"][0], out["weights_sum"][0])
            write_image(staged.temp(depth_path), resize_image(depth, size), depth_path.suffix)
        written = staged.commit()
    coarse, fine = args.samples
    what = f"feature channel {args.features_channel}" if args.features_channel is not None else "rgb"
    _say(
        f"rendered {_describe_size(sr, size)} ({coarse}+{fine} samples, yaw {args.yaw:+g}°, pitch "
        f"{args.pitch:+g}°, {what}; {how}) in {seconds:.2f} s"
    )
    for path in written:
        _say(f"wrote {path}")
    return 0


# ============================================================================================= orbit


def orbit_angles(frames: int, yaw_range: float, pitch_range: float) -> list[tuple[float, float]]:
    """(yaw, pitch offset) per frame of a closed loop, as EG3D's videos: ``yaw = R_y sin(2 pi t)``,
    ``pitch = R_p cos(2 pi t)`` with ``t = i / frames`` (the last frame leads back to the first)."""
    out = []
    for i in range(frames):
        t = 2.0 * math.pi * i / frames
        out.append((yaw_range * math.sin(t), pitch_range * math.cos(t)))
    return out


def cmd_orbit(args: argparse.Namespace) -> int:
    out_path = check_output(args.output, VIDEO_SUFFIXES)
    if not (-90.0 < args.pitch - args.pitch_range and args.pitch + args.pitch_range < 90.0):
        raise CLIError(
            f"--pitch {args.pitch:g} with --pitch-range {args.pitch_range:g} leaves (-90, 90) degrees"
        )
    check_distinct([("triplane", args.triplane)], [("-o", out_path)])
    tri, rtri = render_triplane_file(args.triplane)
    sr, how = choose_superres(args, tri)
    size = args.resolution or (sr.output_resolution if sr is not None else 128)
    angles = orbit_angles(args.frames, args.yaw_range, args.pitch_range)
    cams = np.stack([make_camera(args, yaw=y, pitch=args.pitch + p) for y, p in angles])
    _say(f"orbit: {len(cams)} frames of {_describe_size(sr, size)}; {how}")

    start = time.perf_counter()
    with Staged() as staged:
        writer = VideoWriter(staged.temp(out_path), out_path.suffix, args.fps)
        bar = progress(len(cams), "orbit")
        try:
            for i in range(0, len(cams), args.batch):
                frames, _ = final_images(rtri, cams[i : i + args.batch], args, sr, size, path=args.triplane)
                for frame in frames:
                    writer.add(frame)
                bar.update(len(frames))
            writer.close()
        finally:
            writer.abort()
            bar.close()
        staged.commit()
    seconds = time.perf_counter() - start
    _say(
        f"rendered {len(cams)} frames at {size}² in {seconds:.1f} s "
        f"({seconds / len(cams):.2f} s/frame); wrote {out_path}"
    )
    return 0


# ============================================================================================== mesh


def cmd_mesh(args: argparse.Namespace) -> int:
    out_path = check_output(args.output, MESH_SUFFIXES)
    check_distinct([("triplane", args.triplane)], [("-o", out_path)])
    tri = load_triplane_file(args.triplane)
    from lp3d.mesh import extract_mesh, write_mesh

    start = time.perf_counter()
    mesh = extract_mesh(tri, grid=args.grid, threshold=args.threshold)
    seconds = time.perf_counter() - start
    with Staged() as staged:
        write_mesh(staged.temp(out_path), mesh, fmt=out_path.suffix, ascii_ply=args.ascii)
        staged.commit()
    _say(
        f"marching cubes on a {args.grid}³ density grid at threshold {args.threshold:g}: "
        f"{len(mesh.vertices):,} vertices, {len(mesh.faces):,} triangles in {seconds:.1f} s"
    )
    _say(f"wrote {out_path} ({_human_bytes(out_path.stat().st_size)})")
    return 0


# ============================================================================================== info


def camera_summary(label: np.ndarray) -> dict[str, float]:
    """A camera label as yaw/pitch of its centre about the origin (as ``look_at_camera`` takes them),
    radius and focal length."""
    c2w = np.asarray(label, np.float64)[:16].reshape(4, 4)
    centre = c2w[:3, 3]
    radius = float(np.linalg.norm(centre))
    yaw = math.degrees(math.atan2(centre[0], centre[2]))
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, centre[1] / radius)))) if radius > 0 else 0.0
    return {"yaw_deg": yaw, "pitch_deg": pitch, "radius": radius, "focal": float(label[16])}


def triplane_info(path: Path) -> dict[str, Any]:
    """Everything ``lp3d info`` prints, as plain data."""
    tri = load_triplane_file(path)
    with np.load(path, allow_pickle=False) as npz:
        version = int(npz["format_version"])
    planes = tri.planes.astype(np.float32)
    info: dict[str, Any] = {
        "file": str(path),
        "file_size": path.stat().st_size,
        "format_version": version,
        "planes": {
            "shape": list(tri.planes.shape),
            "dtype": str(tri.planes.dtype),
            "min": float(planes.min()),
            "max": float(planes.max()),
            "mean": float(planes.mean()),
            "std": float(planes.std()),
            "per_plane_std": [float(planes[p].std()) for p in range(3)],
        },
        "decoder": {
            name: {
                "shape": list(a.shape),
                "min": float(a.min()),
                "max": float(a.max()),
                "mean": float(a.mean()),
                "rms": float(np.sqrt(np.mean(np.square(a, dtype=np.float64)))),
            }
            for name, a in (("w0", tri.w0), ("b0", tri.b0), ("w1", tri.w1), ("b1", tri.b1))
        },
        "box_warp": tri.box_warp,
        "box": [-tri.box_warp / 2.0, tri.box_warp / 2.0],
        "ray_start": tri.ray_start,
        "ray_end": tri.ray_end,
        "camera": None if tri.camera is None else camera_summary(tri.camera),
        "source": tri.source,
        "occupancy": None,
    }
    # A hidden unit does nothing when its input row or its output column is all zeros.
    used = np.abs(tri.w0).sum(axis=1) * np.abs(tri.w1).sum(axis=0)
    info["decoder"]["hidden_units_used"] = int(np.count_nonzero(used))
    info["decoder"]["density_bias"] = float(tri.b1[0])
    if tri.occupancy is not None:
        occ = tri.occupancy
        info["occupancy"] = {
            "shape": list(occ.shape),
            "min": float(occ.min()),
            "max": float(occ.max()),
            "fraction_nonzero": float(np.count_nonzero(occ) / occ.size),
        }
    return info


def cmd_info(args: argparse.Namespace) -> int:
    info = triplane_info(args.triplane)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    p, d = info["planes"], info["decoder"]
    lines = [
        f"file:           {info['file']} ({_human_bytes(info['file_size'])}, "
        f"format_version {info['format_version']})",
        f"planes:         {tuple(p['shape'])} {p['dtype']}  (3 planes x 32 channels x "
        f"{p['shape'][2]}x{p['shape'][3]})",
        f"  values:       min {p['min']:.4g}, max {p['max']:.4g}, mean {p['mean']:.4g}, std {p['std']:.4g}; "
        f"std per plane {', '.join(f'{s:.3g}' for s in p['per_plane_std'])}",
        f"decoder:        w0 {tuple(d['w0']['shape'])}, b0 {tuple(d['b0']['shape'])}, "
        f"w1 {tuple(d['w1']['shape'])}, b1 {tuple(d['b1']['shape'])}; "
        f"{d['hidden_units_used']} of {d['w0']['shape'][0]} hidden units used",
    ]
    for name in ("w0", "b0", "w1", "b1"):
        s = d[name]
        lines.append(
            f"  {name}:           min {s['min']:.4g}, max {s['max']:.4g}, mean {s['mean']:.4g}, "
            f"rms {s['rms']:.4g}"
        )
    lines.append(f"  density bias: b1[0] = {d['density_bias']:.4g} (raw density output)")
    lines += [
        f"box:            [{info['box'][0]:g}, {info['box'][1]:g}]^3 (box_warp {info['box_warp']:g})",
        f"rays:           t in [{info['ray_start']:g}, {info['ray_end']:g}]",
    ]
    cam = info["camera"]
    lines.append(
        "camera:         none (the input view is not stored)"
        if cam is None
        else f"camera:         yaw {cam['yaw_deg']:+.1f}°, pitch {cam['pitch_deg']:+.1f}°, "
        f"radius {cam['radius']:.3g}, focal {cam['focal']:.4g}"
    )
    lines.append(f"source:         {info['source'] if info['source'] is not None else 'none'}")
    occ = info["occupancy"]
    lines.append(
        "occupancy:      none (not baked)"
        if occ is None
        else f"occupancy:      {tuple(occ['shape'])} grid, {100 * occ['fraction_nonzero']:.1f}% non-zero, "
        f"range [{occ['min']:.3g}, {occ['max']:.3g}]"
    )
    print("\n".join(lines))
    return 0


# ============================================================================================ encode


def _collect_images(inputs: Sequence[Path]) -> list[Path]:
    """Files as given; folders expand to their images (non-recursive, sorted)."""
    from lp3d.photo import IMAGE_SUFFIXES as PHOTO_SUFFIXES

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
    _check_folder(output.parent if not output.exists() else output, "output folder", output)
    stems: dict[str, Path] = {}
    for img in images:
        if img.stem in stems:
            raise CLIError(f"{img} and {stems[img.stem]} would both write {output / (img.stem + '.npz')}")
        stems[img.stem] = img
    return [output / f"{img.stem}.npz" for img in images], (None if output.exists() else output)


def _model_path(arg: Path | None) -> Path:
    from lp3d.inference import DEFAULT_MODEL

    path = arg if arg is not None else DEFAULT_MODEL
    if not path.exists():
        if arg is None:
            raise CLIError(
                f"no model given and the default model {path} does not exist yet; pass --model "
                "MODEL.onnx (with its MODEL.json) or CHECKPOINT.pt, or train one with python -m lp3d.train"
            )
        raise CLIError(f"--model {path}: no such file")
    return path


def prepare_photo(rgb: np.ndarray, size: int, *, detect: bool, name: str) -> tuple[np.ndarray, str]:
    """(crop (size, size, 3) uint8, a one-line description) of one photo; NoFaceError without a face."""
    from lp3d.photo import NoFaceError, centre_crop, crop_image, detect_face

    h, w = rgb.shape[:2]
    if not detect:
        crop = centre_crop(rgb.shape)
        return crop_image(rgb, crop, size), f"{w}x{h}, centre crop {crop.side:.0f} px (no detection)"
    found = detect_face(rgb)
    if found is None:
        raise NoFaceError(
            f"{name}: no face found; if the photo is already a centred portrait crop, pass --no-detect"
        )
    x, y, bw, bh = found.box
    eyes = f"roll {found.angle_deg:+.1f}°" if found.eyes is not None else "eyes not found, not levelled"
    more = f", {found.n_faces} face candidates (the largest clear one used)" if found.n_faces > 1 else ""
    desc = (
        f"{w}x{h}, face {bw:.0f}x{bh:.0f} at ({x:.0f}, {y:.0f}){more}, {eyes}, crop {found.crop.side:.0f} px"
    )
    return crop_image(rgb, found.crop, size), desc


def _crop_path(dest: Path) -> Path:
    """Where ``lp3d encode --save-crop`` writes the aligned crop of the photo encoded to ``dest``."""
    return dest.with_name(dest.stem + ".crop.png")


def cmd_encode(args: argparse.Namespace) -> int:
    from lp3d.inference import load_encoder
    from lp3d.photo import PhotoError, load_image, to_encoder_input
    from lp3d.triplane_io import save_triplane

    images = _collect_images(args.inputs)
    destinations, new_folder = _plan_outputs(images, args.output)
    crop_paths = [_crop_path(dest) for dest in destinations] if args.save_crop else []
    check_distinct(
        [("photo", img) for img in images],
        [("output", dest) for dest in destinations] + [("crop", crop) for crop in crop_paths],
    )
    model_path = _model_path(args.model)

    t0 = time.perf_counter()
    encoder = load_encoder(model_path, args.backend)
    pkg = encoder.package
    _say(
        f"model: {encoder.description}, config {pkg.config_name!r}, {pkg.image_size}² -> "
        f"{pkg.triplane_resolution}² triplane, loaded in {time.perf_counter() - t0:.2f} s"
    )

    # Read, detect and crop everything first: one bad photo fails the run before anything is written.
    t0 = time.perf_counter()
    crops: list[np.ndarray] = []
    failures: list[str] = []
    for img in images:
        try:
            rgb, notes = load_image(img)
            for note in notes:
                _warn(note)
            crop, desc = prepare_photo(rgb, pkg.image_size, detect=not args.no_detect, name=str(img))
        except PhotoError as e:
            failures.append(str(e))
            continue
        crops.append(crop)
        _say(f"{img}: {desc}")
    if failures:
        if len(failures) == 1:
            raise CLIError(failures[0])
        raise CLIError(f"{len(failures)} of {len(images)} photos cannot be used:\n  " + "\n  ".join(failures))
    t_prep = time.perf_counter() - t0

    t0 = time.perf_counter()
    batch = to_encoder_input(np.stack(crops))
    planes = np.concatenate(
        [encoder.run(batch[i : i + args.batch_size]) for i in range(0, len(batch), args.batch_size)]
    )
    t_enc = time.perf_counter() - t0

    t0 = time.perf_counter()
    with Staged() as staged:
        if new_folder is not None:
            staged.mkdir(new_folder)
        for img, dest, plane, crop in zip(images, destinations, planes, crops, strict=True):
            source = f"lp3d encode {img.name} (model {pkg.config_name}, {encoder.backend})"
            tri = pkg.triplane(plane.astype(np.float16) if args.half else plane, source=source)
            save_triplane(staged.temp(dest), tri)
            if args.save_crop:
                write_image(staged.temp(_crop_path(dest)), crop, ".png")
        written = staged.commit()
    t_write = time.perf_counter() - t0
    n = len(images)
    _say(
        f"timings: detect+crop {t_prep:.2f} s ({t_prep / n:.3f} s/image), encode {t_enc:.2f} s "
        f"({t_enc / n:.3f} s/image, {encoder.backend}), write {t_write:.2f} s"
    )
    for path in written:
        _say(f"wrote {path}")
    return 0


# ============================================================================================= video


def _ffmpeg_reason(e: Exception) -> str:
    """The informative last line of an imageio-ffmpeg error (its message embeds ffmpeg's whole log)."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    tail = [ln for ln in lines if "rror" in ln or "nvalid" in ln or "No such" in ln]
    return (tail[-1] if tail else lines[0] if lines else type(e).__name__)[:300]


#: Longest time ffmpeg may take to scan a video's packets (no decoding: seconds even for long films).
VIDEO_SCAN_TIMEOUT_S = 600.0


def count_video_frames(path: Path) -> int | None:
    """Frames the container holds in its first video stream: its packets, counted by the bundled ffmpeg
    without decoding (so a damaged frame still counts). ``None`` when ffmpeg cannot copy the stream (the
    decoder may still read it). Raises :class:`CLIError` for a file with no video stream (audio only,
    an empty container), whose ffmpeg error would only say "Invalid argument"."""
    import re
    import subprocess

    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", "-i", str(path)]
    cmd += ["-map", "0:v:0", "-c", "copy", "-f", "null", "-"]
    try:
        done = subprocess.run(cmd, capture_output=True, timeout=VIDEO_SCAN_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise CLIError(
            f"{path}: ffmpeg took more than {VIDEO_SCAN_TIMEOUT_S:g} s to scan the video"
        ) from None
    log = done.stderr.decode(errors="replace")
    if "matches no streams" in log:
        what = "an audio stream but no video" if re.search(r"Stream #\S+: Audio:", log) else "no video stream"
        raise CLIError(f"{path}: has {what}")
    counts = re.findall(r"frame=\s*(\d+)", log)
    return int(counts[-1]) if done.returncode == 0 and counts else None


def read_video(path: Path, max_frames: int | None) -> tuple[dict[str, Any], Iterator[np.ndarray]]:
    """(metadata, frames (H, W, 3) uint8) of a video file read by the bundled ffmpeg; ``max_frames=0``
    only reads the metadata, and adds ``frames_declared`` (:func:`count_video_frames`).

    The decoder skips frames it cannot decode (ffmpeg goes on after a damaged frame), so callers
    compare the frames they got with ``frames_declared``: :func:`cmd_video` warns, naming both counts.
    """
    from lp3d.photo import MAX_PIXELS, MAX_SIDE

    if not path.exists():
        raise CLIError(f"{path}: no such file")
    if path.is_dir():
        raise CLIError(f"{path}: is a folder, not a video")
    if not path.is_file():
        raise CLIError(f"{path}: is not a regular file")
    if path.stat().st_size == 0:
        raise CLIError(f"{path}: empty file")
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise CLIError(f"reading videos needs imageio-ffmpeg: {e}") from None
    declared = count_video_frames(path) if max_frames == 0 else None
    if declared == 0:
        raise CLIError(f"{path}: the video stream has no frames")
    try:
        gen = imageio_ffmpeg.read_frames(str(path))
        meta = next(gen)
        w, h = (int(v) for v in meta["size"])
    # imageio-ffmpeg parses ffmpeg's log: besides OSError, an odd log gives Index/Attribute/ValueError.
    except (OSError, RuntimeError, StopIteration, IndexError, AttributeError, ValueError, KeyError) as e:
        raise CLIError(f"{path}: cannot read as a video ({_ffmpeg_reason(e)})") from None
    if not (0 < w * h <= MAX_PIXELS and max(w, h) <= MAX_SIDE):
        gen.close()
        raise CLIError(
            f"{path}: frames are {w}x{h}; need 1 to {MAX_PIXELS / 1e6:.0f} MP and sides up to {MAX_SIDE} px"
        )
    if max_frames == 0:  # a probe: metadata only, stop ffmpeg now
        gen.close()
        return {**meta, "frames_declared": declared}, iter(())

    def frames() -> Iterator[np.ndarray]:
        try:
            for i, raw in enumerate(gen):
                if max_frames is not None and i >= max_frames:
                    break
                yield np.frombuffer(raw, np.uint8).reshape(h, w, 3)
        except (OSError, RuntimeError) as e:
            raise CLIError(f"{path}: error while decoding ({_ffmpeg_reason(e)})") from None
        finally:
            gen.close()

    return meta, frames()


def _frame_estimate(meta: dict[str, Any], max_frames: int | None) -> int | None:
    """Frames to expect (for the progress bar): the container's count, else ffmpeg's duration times fps,
    capped by --max-frames."""
    n = meta.get("frames_declared")
    if n is None:
        try:
            n = round(float(meta["duration"]) * float(meta["fps"]))
        except (KeyError, TypeError, ValueError, OverflowError):
            return max_frames
    n = n if n > 0 else None
    return n if max_frames is None else min(max_frames, n or max_frames)


def _no_frames(path: Path, meta: dict[str, Any]) -> str:
    """The error for a video of which no frame could be decoded."""
    declared = meta.get("frames_declared")
    held = f" of the {declared} the container holds" if declared else ""
    return f"{path}: no frame{held} could be decoded"


def _nearest(hits: np.ndarray, n: int) -> np.ndarray:
    """For each of ``n`` frames, the index in sorted ``hits`` (frames with a face) nearest to it."""
    frames = np.arange(n)
    right = np.clip(np.searchsorted(hits, frames), 0, len(hits) - 1)
    left = np.clip(right - 1, 0, len(hits) - 1)
    use_left = np.abs(hits[left] - frames) <= np.abs(hits[right] - frames)
    return np.where(use_left, hits[left], hits[right])


def _smooth_crops(crops: list[Any], alpha: float) -> list[Any]:
    """Exponential smoothing of the crop parameters, run forward then backward (no lag)."""
    if alpha <= 0 or len(crops) < 2:
        return crops
    keys = ("cx", "cy", "side", "angle_deg")
    vals = np.array([[getattr(c, k) for k in keys] for c in crops], np.float64)
    for i in range(1, len(vals)):
        vals[i] = alpha * vals[i - 1] + (1 - alpha) * vals[i]
    for i in range(len(vals) - 2, -1, -1):
        vals[i] = alpha * vals[i + 1] + (1 - alpha) * vals[i]
    return [
        replace(c, **dict(zip(keys, map(float, v), strict=True))) for c, v in zip(crops, vals, strict=True)
    ]


def cmd_video(args: argparse.Namespace) -> int:
    from lp3d.inference import load_encoder
    from lp3d.photo import (
        DETECT_MAX_SIDE,
        NoFaceError,
        centre_crop,
        crop_image,
        detect_face,
        to_encoder_input,
    )

    out_path = check_output(args.output, VIDEO_SUFFIXES)
    check_distinct([("input video", args.input)], [("-o", out_path)])
    encoder = load_encoder(_model_path(args.model), args.backend, superres=not args.raw)
    pkg, sr = encoder.package, encoder.superres
    size = args.resolution or (sr.output_resolution if sr is not None else 128)
    meta, _ = read_video(args.input, 0)  # fail fast on an unreadable file
    fps = float(args.fps or meta.get("fps") or 25.0)
    w, h = meta["size"]
    if args.raw:
        how = "raw volume render (--raw)"
    elif sr is not None:
        how = f"super-resolved by {sr.description}"
    else:
        how = "raw volume render (the model has no super-resolution network)"
    _say(f"video: {args.input} {w}x{h} at {fps:g} fps; model {encoder.description}")
    _say(f"frames: {_describe_size(sr, size)}; {how}")
    if max(w, h) > 4 * DETECT_MAX_SIDE:
        _warn(f"{w}x{h} frames are large; detection runs on downscaled copies")

    # Pass 1: where the face is in each frame (gaps filled from the nearest detection, then smoothed).
    crops: list[Any] = []
    if args.no_detect:
        crops = []
    else:
        _, frames = read_video(args.input, args.max_frames)
        bar = progress(_frame_estimate(meta, args.max_frames), "detect")
        try:
            for frame in frames:
                found = detect_face(frame)
                crops.append(None if found is None else found.crop)
                bar.update()
        finally:
            bar.close()
        if not crops:
            raise CLIError(_no_frames(args.input, meta))
        hits = [i for i, c in enumerate(crops) if c is not None]
        if not hits:
            raise NoFaceError(
                f"{args.input}: no face found in any frame; for a centred portrait video pass --no-detect"
            )
        if len(hits) < len(crops):
            _warn(f"no face in {len(crops) - len(hits)} of {len(crops)} frames; using the nearest detection")
        crops = [crops[j] for j in _nearest(np.asarray(hits), len(crops))]
        crops = _smooth_crops(crops, VIDEO_CROP_SMOOTHING)

    # Pass 2: crop, encode, smooth the triplane over time, render the new view.
    camera = make_camera(args)[None]
    _, frames = read_video(args.input, args.max_frames)
    start = time.perf_counter()
    t_enc = t_render = 0.0
    state: np.ndarray | None = None
    with Staged() as staged:
        writer = VideoWriter(staged.temp(out_path), out_path.suffix, fps)
        bar = progress(len(crops) if crops else _frame_estimate(meta, args.max_frames), "video")
        try:
            for i, frame in enumerate(frames):
                crop = crops[min(i, len(crops) - 1)] if crops else centre_crop(frame.shape)
                face = crop_image(frame, crop, pkg.image_size)
                t0 = time.perf_counter()
                planes = encoder.run(to_encoder_input(face[None]))[0]
                t_enc += time.perf_counter() - t0
                state = planes if state is None else args.smooth * state + (1.0 - args.smooth) * planes
                t0 = time.perf_counter()
                image = final_images(render_triplane(pkg.triplane(state)), camera, args, sr, size)[0][0]
                t_render += time.perf_counter() - t0
                if args.side_by_side:
                    image = np.concatenate([resize_image(face, size), image], axis=1)
                writer.add(image)
                bar.update()
            if writer.count == 0:
                raise CLIError(_no_frames(args.input, meta))
            writer.close()
        finally:
            writer.abort()
            bar.close()
        staged.commit()
    n = writer.count
    declared = meta["frames_declared"]
    expected = declared if declared is None or args.max_frames is None else min(declared, args.max_frames)
    if expected is not None and n < expected:
        # A damaged file: ffmpeg skipped frames it could not decode. Warn rather than fail, so a long
        # video with one bad frame still lifts, but never silently.
        _warn(
            f"{args.input}: decoded {n} of the {expected} frames the container holds (damaged frames are "
            f"skipped); the output has {n} frames"
        )
    total = time.perf_counter() - start
    _say(
        f"lifted {n} frames in {total:.1f} s (encode {t_enc / n:.3f} s/frame, render {t_render / n:.3f} "
        f"s/frame at {size}²); wrote {out_path}"
    )
    return 0


# ============================================================================================== demo


def cmd_demo(args: argparse.Namespace) -> int:
    from lp3d.demo import run

    return run(args)


# ============================================================================================ parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="lp3d: single portrait photo -> 3D (EG3D triplane), rendered in real time.",
        epilog="Run 'lp3d COMMAND --help' for each command's options.",
    )
    from lp3d import __version__ as version

    parser.add_argument("--version", action="version", version=f"lp3d {version}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    # encode
    p = sub.add_parser(
        "encode",
        help="photo(s) -> triplane .npz (detect, align, crop, encode)",
        description="Encode portrait photos into triplane files. Each photo is read, the "
        "largest face is detected (OpenCV Haar cascades), levelled by its eye line and "
        "cropped to the training framing, then encoded.",
    )
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
        "lp3d/models/small.onnx in the package)",
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
        "--batch-size", type=_int_in(1, 256), default=4, help="images per encoder call (default: 4)"
    )
    p.add_argument("--half", action="store_true", help="store the planes as float16 (half the file size)")
    p.add_argument(
        "--save-crop", action="store_true", help="also write the aligned input crop as <name>.crop.png"
    )
    p.set_defaults(func=cmd_encode)

    # render
    p = sub.add_parser(
        "render",
        help="render one view of a triplane to an image",
        description="Render one view of a triplane .npz to a PNG/JPEG image.",
    )
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output image (.png, .jpg)")
    _camera_args(p)
    _render_args(p, 256)
    p.add_argument("--depth", type=Path, default=None, help="also write the depth map (near = bright) here")
    p.add_argument(
        "--features-channel",
        type=_int_in(0, 31),
        default=None,
        metavar="K",
        help="write decoder feature channel K (0-31, grayscale) of the raw render instead of the image",
    )
    _superres_model_arg(p)
    p.set_defaults(func=cmd_render)

    # orbit
    p = sub.add_parser(
        "orbit",
        help="render a turntable video (.gif or .mp4)",
        description="Render a closed camera loop around a triplane: yaw = R sin(2 pi t), "
        "pitch = pitch + P cos(2 pi t).",
    )
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output video (.gif or .mp4)")
    p.add_argument("--frames", type=_int_in(1, 10000), default=36, help="frames in the loop (default: 36)")
    p.add_argument(
        "--yaw-range", type=_float_in(0.0, 89.0), default=35.0, help="yaw amplitude in degrees (default: 35)"
    )
    p.add_argument(
        "--pitch-range",
        type=_float_in(0.0, 60.0),
        default=0.0,
        help="pitch amplitude in degrees (default: 0)",
    )
    p.add_argument("--fps", type=_float_in(0.1, 120.0), default=18.0, help="frames per second (default: 18)")
    p.add_argument("--batch", type=_int_in(1, 64), default=4, help="frames per render call (default: 4)")
    _camera_args(p, yaw=None)
    _render_args(p, 128)
    _superres_model_arg(p)
    p.set_defaults(func=cmd_orbit)

    # mesh
    from lp3d.mesh import EG3D_MESH_THRESHOLD

    p = sub.add_parser(
        "mesh",
        help="extract a coloured mesh (.ply, .obj, .glb) with marching cubes",
        description="Sample the decoder's raw density on a grid inside the triplane box, "
        "run marching cubes and colour the vertices with the decoder's RGB.",
    )
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output mesh (.ply, .obj or .glb)")
    p.add_argument("--grid", type=_int_in(8, 512), default=128, help="grid points per axis (default: 128)")
    p.add_argument(
        "--threshold",
        type=float,
        default=EG3D_MESH_THRESHOLD,
        help="raw density level of the surface (default: %(default)s, as EG3D)",
    )
    p.add_argument("--ascii", action="store_true", help="ASCII instead of binary PLY")
    p.set_defaults(func=cmd_mesh)

    # info
    p = sub.add_parser(
        "info",
        help="describe a triplane file",
        description="Print what a triplane .npz holds: planes, decoder, bounds, camera, "
        "source, occupancy, size and format version.",
    )
    p.add_argument("triplane", type=Path, help="triplane .npz file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=cmd_info)

    # video
    p = sub.add_parser(
        "video",
        help="lift a portrait video to a new viewpoint, frame by frame",
        description="For every frame: detect and crop the face, encode it, optionally "
        "smooth the triplane over time, and render it from the given view.",
    )
    p.add_argument("input", type=Path, help="input video (anything ffmpeg reads)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output video (.mp4 or .gif)")
    p.add_argument(
        "--smooth",
        type=_float_in(0.0, 1.0, hi_open=True),
        default=0.0,
        help="temporal smoothing of the triplane, state = s * state + (1 - s) * new "
        "(0 = off, default; 0.5 is moderate)",
    )
    p.add_argument("--no-detect", action="store_true", help="skip face detection (centre square crop)")
    p.add_argument("--model", type=Path, default=None, help="as for encode")
    p.add_argument("--backend", choices=("onnx", "torch"), default=None, help="as for encode")
    p.add_argument("--max-frames", type=_int_in(1, 10**7), default=None, help="stop after this many frames")
    p.add_argument(
        "--fps", type=_float_in(0.1, 240.0), default=None, help="output fps (default: the input's)"
    )
    p.add_argument("--side-by-side", action="store_true", help="put the input crop left of the new view")
    _camera_args(p, yaw=20.0)
    _render_args(p, 128)
    p.set_defaults(func=cmd_video)

    # demo
    p = sub.add_parser(
        "demo",
        help="photo in, 3D out: lift a teacher portrait and a real photo with the shipped model",
        description="Encode a built-in teacher portrait and scikit-image's astronaut with the shipped "
        "model; write their triplanes, a side-by-side PNG and an orbit GIF.",
    )
    from lp3d.demo import add_arguments as demo_arguments

    demo_arguments(p)
    p.set_defaults(func=cmd_demo)
    return parser


def _format_error(e: BaseException) -> str:
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or e}"
    return str(e) or type(e).__name__


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 error, 2 usage, 130 interrupted)."""
    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as e:  # --help/--version (0) or a usage error (2); argparse has printed it
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    from lp3d.model_package import ModelPackageError

    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print(f"{PROG} {args.command}: interrupted", file=sys.stderr)
        return 130
    except (CLIError, ModelPackageError, ValueError, OSError) as e:
        if os.environ.get("LP3D_DEBUG"):
            raise
        print(f"{PROG} {args.command}: error: {_format_error(e)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
