"""Writing a command's outputs: staged (atomic) files with one-line errors, checks made before any
slow work (format, folder, no output replacing an input), image and video writers, progress bars.

Used by the command line (:mod:`lp3d.cli`) and anything else that writes user-named files. Every
error is a :class:`lp3d.errors.UserError` naming the destination, never a temporary file.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.atomic import StagedFiles
from lp3d.errors import UserError

__all__ = [
    "IMAGE_SUFFIXES",
    "MESH_SUFFIXES",
    "VIDEO_SUFFIXES",
    "Staged",
    "VideoWriter",
    "check_distinct",
    "check_folder",
    "check_output",
    "progress",
    "write_image",
]

#: Output formats per kind of output (``lp3d.photo.PHOTO_SUFFIXES`` are the photos it reads).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".gif")
MESH_SUFFIXES = (".ply", ".obj", ".glb")


class Staged(StagedFiles):
    """Command outputs: :class:`lp3d.atomic.StagedFiles` (temporary files beside their
    destinations, published together by :meth:`commit`, all deleted on failure) whose write errors
    are one-line :class:`UserError` messages naming the destination, never a temporary file."""

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        final = self.destination(exc.filename) if isinstance(exc, OSError) else None
        super().__exit__(exc_type, exc, tb)
        if final is not None and isinstance(exc, OSError):
            raise UserError(f"cannot write {final}: {exc.strerror or exc}") from exc

    def temp(self, final: str | os.PathLike[str]) -> Path:
        try:
            return super().temp(final)
        except OSError as e:
            raise UserError(f"cannot write {final}: {e.strerror or e}") from None

    def commit(self) -> list[Path]:
        try:
            return super().commit()
        except OSError as e:
            failed = self.destination(e.filename) or self.destinations[-1]
            self.discard()
            raise UserError(f"cannot write {failed}: {e.strerror or e}") from None


def check_output(path: Path, suffixes: Sequence[str], what: str = "output") -> Path:
    """Fail early (before any slow work) if ``path`` cannot be written as one of ``suffixes``."""
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        raise UserError(
            f"{what} {path}: unsupported format {suffix or '(no suffix)'}; use one of {', '.join(suffixes)}"
        )
    if path.is_dir():
        raise UserError(f"{what} {path} is a folder; give a file name")
    check_folder(path.parent, what, path)
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
                raise UserError(
                    f"{what} {path} is the same file as the {other_what} {other}: writing it would "
                    "destroy the input; choose another output name"
                )
            raise UserError(f"{what} {path} and {other_what} {other} name the same file")
        seen[key] = (what, path, False)


def check_folder(folder: Path, what: str, path: Path) -> None:
    if not folder.exists():
        raise UserError(f"{what} {path}: folder {folder} does not exist")
    if not folder.is_dir():
        raise UserError(f"{what} {path}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UserError(f"{what} {path}: folder {folder} is not writable")


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
            raise UserError(f"MP4 output needs imageio-ffmpeg (pip install imageio-ffmpeg): {e}") from None
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
                raise UserError("no frames to write")
            import imageio.v3 as iio

            iio.imwrite(
                self.path, np.stack(self.frames), extension=".gif", duration=1000.0 / self.fps, loop=0
            )
        elif self._mp4 is not None:
            gen, self._mp4 = self._mp4, None
            gen.close()
        elif self.count == 0:
            raise UserError("no frames to write")

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
