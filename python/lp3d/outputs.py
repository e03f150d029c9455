"""Writing a command's outputs: staged (atomic) files with one-line errors, checks made before any
slow work (format, folder, no output replacing an input), image and video writers, progress bars.

Used by the command line (:mod:`lp3d.cli`) and anything else that writes user-named files. Every
error is a :class:`lp3d.errors.UserError` naming the destination, never a temporary file.
"""

from __future__ import annotations

import contextlib
import errno
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
    "Staged",
    "VIDEO_SUFFIXES",
    "VideoWriter",
    "check_distinct",
    "check_folder",
    "check_output_folder",
    "check_output",
    "gif_bytes",
    "progress",
    "write_image",
]

#: Output formats per kind of output (``lp3d.photo.PHOTO_SUFFIXES`` are the photos it reads).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".gif")
MESH_SUFFIXES = (".ply", ".obj", ".glb")


#: Errors of a write that may come without a file name: a full disk or quota, a file too large, I/O.
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})


class Staged(StagedFiles):
    """Command outputs: :class:`lp3d.atomic.StagedFiles` (temporary files beside their
    destinations, published together by :meth:`commit`, all deleted on failure) whose write errors
    are one-line :class:`UserError` messages naming the destination, never a temporary file."""

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        final = self._about(exc) if isinstance(exc, OSError) else None
        super().__exit__(exc_type, exc, tb)
        if final is not None and isinstance(exc, OSError):
            raise UserError(f"cannot write {final}: {exc.strerror or exc}") from exc

    def _about(self, exc: OSError) -> str | None:
        """The destination an error is about: the one it names, or for an error that names no file (a
        full disk found by ``write`` on an open file) the staged destination(s) being written."""
        if exc.filename is not None:
            final = self.destination(exc.filename)
            return None if final is None else str(final)
        if exc.errno not in _WRITE_ERRNOS or not self.destinations:
            return None
        names = [str(p) for p in self.destinations]
        return names[0] if len(names) == 1 else f"one of {', '.join(names)}"

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


def _check_cwd(what: str, path: Path) -> None:
    """A relative ``path`` needs a working directory: one that was removed (``cd dir; rm -r ../dir``)
    is named here rather than as a bare "No such file or directory" without a file name."""
    if path.is_absolute():
        return
    try:
        os.getcwd()
    except FileNotFoundError:
        raise UserError(
            f"{what} {path}: the working directory was removed, so a relative path names no folder; "
            "cd to an existing folder or give an absolute path"
        ) from None


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
    for what, path in [*inputs, *outputs]:
        _check_cwd(what, path)
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
    _check_cwd(what, path)
    if not folder.exists():
        raise UserError(f"{what} {path}: folder {folder} does not exist")
    if not folder.is_dir():
        raise UserError(f"{what} {path}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UserError(f"{what} {path}: folder {folder} is not writable")


def check_output_folder(folder: Path, what: str = "--out") -> None:
    """Refuse, before any work, an output folder that cannot be one: a file of that name, or a
    folder that is not writable. A missing folder is made later, by the command that fills it."""
    _check_cwd(what, folder)
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{what} {folder}: is a file, not a folder")
    if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
        raise UserError(f"{what} {folder}: folder is not writable")


def _named(e: OSError, path: Path) -> OSError:
    """``e`` naming ``path`` when it names no file: a full disk found by ``write`` or ``flush`` on an
    open file is an ``OSError`` without a file name ("No space left on device", but where?)."""
    if e.filename is None:
        e.filename = str(path)
    return e


def write_image(path: Path, image: np.ndarray, fmt_suffix: str) -> None:
    """Write (H, W, 3) or (H, W) uint8 as PNG or JPEG (by ``fmt_suffix``). A write error names
    ``path``."""
    from PIL import Image

    fmt = "PNG" if fmt_suffix.lower() == ".png" else "JPEG"
    kwargs = {"quality": 95} if fmt == "JPEG" else {}
    try:
        with open(path, "wb") as f:
            Image.fromarray(np.ascontiguousarray(image)).save(f, format=fmt, **kwargs)
    except OSError as e:
        raise _named(e, path) from None


def gif_bytes(frames: Sequence[np.ndarray], fps: float) -> bytes:
    """Frames (H, W, 3) uint8 as an endlessly looping GIF (Pillow), in memory."""
    import io

    from PIL import Image

    if not frames:
        raise UserError("no frames to write")
    images = [Image.fromarray(np.ascontiguousarray(f, dtype=np.uint8)) for f in frames]
    more = {"save_all": True, "append_images": images[1:]} if len(images) > 1 else {}
    out = io.BytesIO()
    images[0].save(out, format="GIF", duration=1000.0 / fps, loop=0, **more)
    return out.getvalue()


class VideoWriter:
    """Frames (H, W, 3) uint8 into a ``.gif`` (Pillow, written on :meth:`close`) or an ``.mp4``
    (H.264 by the ffmpeg binary bundled with imageio-ffmpeg, streamed to its stdin).

    Every failure is an ``OSError`` naming :attr:`path` (so :class:`Staged` names the destination): a
    full disk, or ffmpeg failing for any reason — its exit status is checked, so a video it could not
    finish is never reported as written."""

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
                self._mp4 = _Ffmpeg(self.path, frame.shape[1], frame.shape[0], self.fps)
            self._mp4.send(frame)
        self.count += 1

    def close(self) -> None:
        if self.suffix == ".gif":
            if not self.frames:
                raise UserError("no frames to write")
            self._write_gif()
        elif self._mp4 is not None:
            mp4, self._mp4 = self._mp4, None
            mp4.close()
        elif self.count == 0:
            raise UserError("no frames to write")

    def _write_gif(self) -> None:
        data = gif_bytes(self.frames, self.fps)
        try:
            with open(self.path, "wb") as f:
                f.write(data)
        except OSError as e:
            raise _named(e, self.path) from None

    def abort(self) -> None:
        if self._mp4 is not None:
            self._mp4.kill()
            self._mp4 = None


class _Ffmpeg:
    """An ffmpeg process encoding raw RGB frames from its stdin to H.264 in ``path`` (yuv420p, the
    sides made even), whose failure is an ``OSError`` naming ``path`` with ffmpeg's own reason."""

    def __init__(self, path: Path, width: int, height: int, fps: float) -> None:
        import subprocess
        import threading
        from fractions import Fraction

        try:
            import imageio_ffmpeg

            exe = imageio_ffmpeg.get_ffmpeg_exe()
        except (ImportError, RuntimeError) as e:
            raise UserError(f"MP4 output needs imageio-ffmpeg (pip install imageio-ffmpeg): {e}") from None
        self.path = path
        even = ["-vf", f"scale={width + width % 2}:{height + height % 2}"] if width % 2 or height % 2 else []
        rate = str(Fraction(fps).limit_denominator())
        cmd = [exe, "-y", "-v", "error", "-f", "rawvideo", "-vcodec", "rawvideo", "-s", f"{width}x{height}"]
        cmd += [
            "-pix_fmt",
            "rgb24",
            "-r",
            rate,
            "-i",
            "-",
            "-an",
            "-vcodec",
            "libx264",
            "-pix_fmt",
            "yuv420p",
        ]
        cmd += ["-crf", "10", *even, str(path)]  # crf 10: imageio-ffmpeg's quality 8
        # Its own session: Ctrl-C in the terminal reaches lp3d, which stops it (no half-written trailer).
        self.proc = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        self.log: list[bytes] = []  # its stderr, read as it comes so that a full pipe never blocks it
        self._reader = threading.Thread(target=self._read_log, daemon=True)
        self._reader.start()

    def _read_log(self) -> None:
        for line in self.proc.stderr:
            if len(self.log) < 200:
                self.log.append(line)

    def send(self, frame: np.ndarray) -> None:
        try:
            self.proc.stdin.write(frame.tobytes())
        except OSError:  # ffmpeg has exited (a full disk, a bad path): its exit status says why
            self.close()
            raise OSError(errno.EIO, "the video encoder ffmpeg stopped", str(self.path)) from None

    def close(self) -> None:
        """Finish the file: wait for ffmpeg and check how it ended."""
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        code = self.proc.wait()
        self._reader.join()
        if code != 0:
            text = b"".join(self.log).decode(errors="replace")
            lines = [line.strip() for line in text.splitlines() if line.strip()]
            if "No space left on device" in text:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
            why = lines[-1] if lines else f"exit status {code}"
            raise OSError(errno.EIO, f"the video encoder ffmpeg failed: {why}", str(self.path))

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        self.proc.wait()
        self._reader.join()


def progress(total: int | None, desc: str, unit: str = "frame") -> Any:
    """A tqdm progress bar on stderr counting ``unit``s (a no-op object when tqdm is missing)."""
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency

        class _Null:
            def update(self, n: int = 1) -> None: ...
            def close(self) -> None: ...
            def set_postfix_str(self, s: str) -> None: ...

        return _Null()
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=True)
