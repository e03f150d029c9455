"""Photos and videos in: `lp3d encode` and `lp3d video` on damaged, odd and hostile media.

Targeted cases first: an animated GIF used as a photo warns that only its first frame is used; a
damaged mp4 that decodes to fewer frames than its container holds warns with both counts; a file with
no video stream (audio only, an empty container) or a video stream without frames is a clear error
naming the file, not ffmpeg's "Invalid argument".

Then two seeded fuzzers that mutate small valid files made here (PNG, JPEG, GIF; mp4, GIF) and run
each through the command line in-process. Every case must end in a clean error (exit status 1, one
``lp3d <command>: error: ...`` line, nothing written) or a valid output (a triplane that loads, a video
that decodes) - never a traceback, a hang (each case runs under a deadline) or a partial output. The
encoder is the randomly initialised ``tiny`` configuration exported to ONNX here and loaded once; the
renders are 8² with 4+4 samples.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import zlib
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.cli import main
from lp3d.render.triplane_io import load_triplane
from support.deadline import Hang, deadline
from support.tiny_model import tiny_onnx_package

VIDEO_SMALL = ["--resolution", "8", "--samples", "4+4"]
#: Fuzz cases per run (the counts docs/reliability.md quotes). For a longer hunt, scale them and pick
#: another seed: ``LP3D_FUZZ_SCALE=20 LP3D_FUZZ_SEED=5 pytest tests/robustness/test_media_fuzz.py -k fuzz``.
SCALE = float(os.environ.get("LP3D_FUZZ_SCALE", "1"))
SEED = int(os.environ.get("LP3D_FUZZ_SEED", "11"))
IMAGE_CASES = round(400 * SCALE)
VIDEO_CASES = round(64 * SCALE)
#: A case running longer than this is a hang (normal cases take well under a second).
DEADLINE_S = 60.0


# =========================================================================================== fixtures


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A randomly initialised ``tiny`` encoder as ONNX with its sidecar."""
    return tiny_onnx_package(tmp_path_factory.mktemp("model"))[0]


@pytest.fixture(scope="module")
def encoders() -> dict[tuple[str, str | None], object]:
    return {}


@pytest.fixture(autouse=True)
def load_encoder_once(monkeypatch: pytest.MonkeyPatch, encoders: dict) -> None:
    """Each `lp3d` call loads the model again; the fuzzers make hundreds of calls, so keep one."""
    import lp3d.lift.inference

    real = lp3d.lift.inference.load_encoder

    def load(path: Path, backend: str | None = None, *, superres: bool = False) -> object:
        key = (str(path), backend, superres)
        if key not in encoders:
            encoders[key] = real(path, backend, superres=superres)
        return encoders[key]

    monkeypatch.setattr(lp3d.lift.inference, "load_encoder", load)


def face(size: int) -> np.ndarray:
    """skimage's astronaut, her face cropped and resized to ``size``²."""
    from skimage.data import astronaut

    return np.asarray(Image.fromarray(astronaut()[:300, 80:380]).resize((size, size), Image.BILINEAR))


def frames(n: int, size: int) -> list[np.ndarray]:
    """``n`` frames of a slowly panning face."""
    big = face(size + 2 * n)
    return [np.ascontiguousarray(big[n : n + size, i : i + size]) for i in range(n)]


def write_mp4(path: Path, images: list[np.ndarray], *params: str) -> Path:
    import imageio_ffmpeg

    h, w = images[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (w, h),
        fps=8,
        macro_block_size=2,
        ffmpeg_log_level="error",
        output_params=["-threads", "1", *params],  # one thread: the same bytes on every run
    )
    writer.send(None)
    for image in images:
        writer.send(image.tobytes())
    writer.close()
    return path


def write_gif(path: Path, images: list[np.ndarray]) -> Path:
    first, *rest = (Image.fromarray(im) for im in images)
    first.save(path, save_all=bool(rest), append_images=rest, duration=100, loop=0)
    return path


def ffmpeg(*args: str) -> None:
    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-nostdin", "-y", *args]
    subprocess.run(cmd, check=True, capture_output=True, timeout=60)


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    """``lp3d ARGV`` in-process: (exit status, stdout, stderr)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def decoded_frames(path: Path) -> int:
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    next(reader)
    return sum(1 for _ in reader)


# ================================================================================ targeted cases


def test_animated_gif_photo_warns_that_only_the_first_frame_is_used(capsys, model, tmp_path) -> None:
    """It was encoded from its first frame with no word."""
    gif = write_gif(tmp_path / "anim.gif", frames(3, 64))
    code, _, err = run(capsys, "encode", gif, "-o", tmp_path / "anim.npz", "--model", model, "--no-detect")
    assert code == 0, err
    assert (
        "warning: anim.gif: has 3 frames (an animated or multi-page GIF image); only the first is used" in err
    )
    # The first frame is the one encoded: the same pixels as a PNG give the same triplane.
    with Image.open(gif) as im:
        first = np.asarray(im.convert("RGB"))
    Image.fromarray(first).save(tmp_path / "first.png")
    code, _, err = run(
        capsys,
        "encode",
        tmp_path / "first.png",
        "-o",
        tmp_path / "first.npz",
        "--model",
        model,
        "--no-detect",
    )
    assert code == 0 and "frames" not in err, err
    np.testing.assert_array_equal(
        load_triplane(tmp_path / "anim.npz").planes, load_triplane(tmp_path / "first.npz").planes
    )
    # A still GIF says nothing.
    write_gif(tmp_path / "still.gif", frames(1, 64))
    code, _, err = run(
        capsys,
        "encode",
        tmp_path / "still.gif",
        "-o",
        tmp_path / "still.npz",
        "--model",
        model,
        "--no-detect",
    )
    assert code == 0 and "frames" not in err, err


def test_photos_the_crop_cannot_take_are_refused(capsys, model, tmp_path) -> None:
    """A 40000 x 16 photo (0.6 MP) crashed OpenCV's warpAffine (sides must be < 32767) with a
    traceback; a FIFO would block the reader forever."""
    wide = tmp_path / "wide.png"
    Image.new("RGB", (40000, 16), (90, 60, 40)).save(wide)
    fifo = tmp_path / "fifo.png"
    os.mkfifo(fifo)
    for src, words in (
        (wide, "wide.png: image is 40000x16, a side over 32766 px"),
        (fifo, "not a regular file"),
    ):
        with deadline(DEADLINE_S):  # opening the FIFO blocked forever
            code, _, err = run(
                capsys, "encode", src, "-o", tmp_path / "o.npz", "--model", model, "--no-detect"
            )
        assert code == 1 and words in err and "Traceback" not in err, err
    assert not (tmp_path / "o.npz").exists()


def damage_last_frame(mp4: Path) -> None:
    """Make the last frame of an H.264 mp4 (one chunk, as ffmpeg writes short files) undecodable: its
    slice's length prefix claims 16 MB. The container still lists all frames."""
    data = bytearray(mp4.read_bytes())
    i = 0
    while data[i + 4 : i + 8] != b"mdat":
        i += struct.unpack(">I", data[i : i + 4])[0]
    end, i = i + struct.unpack(">I", data[i : i + 4])[0], i + 8
    slices = []
    while i + 4 <= end:
        n = struct.unpack(">I", data[i : i + 4])[0]
        if data[i + 4] & 0x1F in (1, 5):  # a coded slice (non-IDR or IDR)
            slices.append(i)
        i += 4 + n
    data[slices[-1] : slices[-1] + 4] = struct.pack(">I", 0xFFFFFF)
    mp4.write_bytes(bytes(data))


def test_damaged_video_warns_how_many_frames_were_decoded(capsys, model, tmp_path) -> None:
    """A damaged mp4 gave 7 of its 8 frames silently."""
    # Intra frames only: no other frame refers to the damaged one, so exactly one is lost.
    src = write_mp4(tmp_path / "in.mp4", frames(8, 48), "-g", "1")
    damage_last_frame(src)
    assert decoded_frames(src) == 7
    out = tmp_path / "out.mp4"
    code, stdout, err = run(capsys, "video", src, "-o", out, "--model", model, "--no-detect", *VIDEO_SMALL)
    assert code == 0, err
    assert f"warning: {src}: decoded 7 of the 8 frames the container holds" in err
    assert "lifted 7 frames" in stdout and decoded_frames(out) == 7
    # --max-frames below what decodes: nothing is missing, nothing to say.
    code, _, err = run(
        capsys,
        "video",
        src,
        "-o",
        tmp_path / "o.gif",
        "--model",
        model,
        "--no-detect",
        "--max-frames",
        5,
        *VIDEO_SMALL,
    )
    assert code == 0 and "decoded" not in err, err


def test_files_without_video_frames_are_named_clearly(capsys, model, tmp_path) -> None:
    """Audio-only and frameless videos failed with ffmpeg's "Invalid argument"."""
    ffmpeg("-f", "lavfi", "-i", "sine=frequency=440:duration=0.5", str(tmp_path / "speech.m4a"))
    ffmpeg("-f", "lavfi", "-i", "sine=frequency=440:duration=0.5", str(tmp_path / "speech.mp4"))
    lavfi = ["-f", "lavfi", "-i", "testsrc=size=32x32:rate=8", "-frames:v", "0"]
    ffmpeg(*lavfi, "-pix_fmt", "yuv420p", str(tmp_path / "empty.mp4"))  # no stream at all
    ffmpeg(*lavfi, str(tmp_path / "frameless.avi"))  # a video stream with no frames
    expected = {
        "speech.m4a": "speech.m4a: has an audio stream but no video",
        "speech.mp4": "speech.mp4: has an audio stream but no video",
        "empty.mp4": "empty.mp4: has no video stream",
        "frameless.avi": "frameless.avi: the video stream has no frames",
    }
    for name, words in expected.items():
        code, _, err = run(
            capsys, "video", tmp_path / name, "-o", tmp_path / "out.mp4", "--model", model, *VIDEO_SMALL
        )
        assert code == 1 and words in err and "Invalid argument" not in err, err
        assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out.mp4").exists()


# ========================================================================================= fuzzers


def mutate(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One to three random edits: flipped bytes, a truncation, an overwritten, deleted or repeated run,
    or an extreme value written over a header word (sizes, counts, lengths live there)."""
    b = bytearray(data)
    done = []
    for _ in range(int(rng.integers(1, 4))):
        n = len(b)
        if n < 2:
            break
        kind = int(rng.integers(6))
        at = int(rng.integers(n))
        run_len = int(rng.integers(1, 65))
        if kind == 0:
            for i in rng.integers(0, n, int(rng.integers(1, 9))):
                b[i] = int(rng.integers(256))
            done.append("flip")
        elif kind == 1:
            del b[at:]
            done.append(f"truncate@{at}")
        elif kind == 2:
            b[at : at + run_len] = rng.integers(0, 256, min(run_len, n - at), dtype=np.uint8).tobytes()
            done.append(f"overwrite@{at}+{run_len}")
        elif kind == 3:
            del b[at : at + run_len]
            done.append(f"delete@{at}+{run_len}")
        elif kind == 4:
            b[at:at] = b[at : at + run_len]
            done.append(f"repeat@{at}+{run_len}")
        else:
            at = int(rng.integers(min(n, 96)))
            word = [b"\x00\x00", b"\xff\xff", b"\x7f\xff\xff\xff", b"\x00\x00\x00\x00", b"\xff\xff\xff\xff"]
            value = word[int(rng.integers(len(word)))]
            b[at : at + len(value)] = value
            done.append(f"header@{at}={value.hex()}")
    return bytes(b), "+".join(done)


def fix_png_crcs(data: bytes) -> bytes:
    """Recompute every chunk checksum of a (mutated) PNG, so the edits reach the chunk parsers and the
    zlib stream instead of all stopping at the first CRC check."""
    b = bytearray(data)
    i = 8
    while i + 12 <= len(b):
        n = struct.unpack(">I", b[i : i + 4])[0]
        if i + 12 + n > len(b):
            break
        b[i + 8 + n : i + 12 + n] = struct.pack(">I", zlib.crc32(b[i + 4 : i + 8 + n]))
        i += 12 + n
    return bytes(b)


PROGRESS = re.compile(r"^\s*(detect|video):")


def check_case(
    code: int,
    err: str,
    command: str,
    folder: Path,
    inputs: set[str],
    output: Path,
    valid: Callable[[Path], None],
) -> str:
    """'ok' or 'error' for a case that kept the promise; an AssertionError otherwise."""
    assert "Traceback" not in err, err
    lines = [ln for ln in re.split(r"[\r\n]+", err) if ln.strip()]
    names = {p.name for p in folder.iterdir()}
    if code == 0:
        assert names == inputs | {output.name}, f"stray files: {names}"
        assert all(ln.startswith("warning: ") or PROGRESS.match(ln) for ln in lines), err
        valid(output)
        return "ok"
    assert code == 1, f"exit status {code}: {err}"
    assert names == inputs, f"a failed run left files: {names - inputs}"
    assert lines and lines[-1].startswith(f"lp3d {command}: error: "), err
    assert all(ln.startswith("warning: ") or PROGRESS.match(ln) for ln in lines[:-1]), err
    return "error"


def fuzz(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    seeds: dict[str, bytes],
    cases: int,
    argv: Callable[[Path, Path, int], list[object]],
    out_suffix: Callable[[int], str],
    valid: Callable[[Path], None],
    command: str,
) -> Counter[str]:
    """Run the seeds unchanged, then ``cases`` mutants (seeded, so every run tries the same files).
    Returns the outcome counts; a broken promise fails with the case's name, seed and edits, and the
    file is kept in ``tmp_path/failed``."""
    rng = np.random.default_rng(SEED)
    outcomes: Counter[str] = Counter()
    names = sorted(seeds)
    plan = [(name, None) for name in names] + [(names[i % len(names)], i) for i in range(cases)]
    for name, i in plan:
        data, edits = (seeds[name], "none") if i is None else mutate(seeds[name], rng)
        if i is not None and name.endswith(".png") and rng.random() < 0.5:
            data, edits = fix_png_crcs(data), edits + "+crc"
        folder = tmp_path / f"case-{'seed' if i is None else i}"
        folder.mkdir()
        src = folder / f"in{Path(name).suffix}"
        src.write_bytes(data)
        k = -1 if i is None else i  # the seeds run as case -1: no face detection
        out = folder / f"out{out_suffix(k)}"
        try:
            with deadline(DEADLINE_S):
                code, _, err = run(capsys, *argv(src, out, k))
            outcome = check_case(code, err, command, folder, {src.name}, out, valid)
        except (Exception, Hang) as e:  # anything escaping main() is a broken promise too
            keep = tmp_path / "failed"
            keep.mkdir(exist_ok=True)
            (keep / f"{i}-{name}").write_bytes(data)
            raise AssertionError(f"case {i} ({name}, edits {edits}): {type(e).__name__}: {e}") from None
        assert i is not None or outcome == "ok", f"the unmodified seed {name} failed: {err}"
        outcomes[outcome] += 1
        for p in folder.iterdir():
            p.unlink()
        folder.rmdir()
    return outcomes


def image_seeds() -> dict[str, bytes]:
    import io

    def encoded(image: Image.Image, fmt: str, **kw: object) -> bytes:
        buf = io.BytesIO()
        image.save(buf, format=fmt, **kw)
        return buf.getvalue()

    still = Image.fromarray(face(48))
    anim = [Image.fromarray(f) for f in frames(3, 40)]
    return {
        "face.png": encoded(still, "PNG"),
        "face.jpg": encoded(still, "JPEG", quality=85),
        "grey.png": encoded(still.convert("L"), "PNG"),
        "anim.gif": encoded(anim[0], "GIF", save_all=True, append_images=anim[1:], duration=80, loop=0),
    }


def test_fuzz_photos_through_encode(capsys, model, tmp_path) -> None:
    """Damaged PNG/JPEG/GIF photos: a clean error or a triplane that loads."""
    outcomes = fuzz(
        capsys,
        tmp_path,
        image_seeds(),
        IMAGE_CASES,
        # Every fifth case runs face detection; the rest the centre crop, which reaches the encoder.
        lambda src, out, i: ["encode", src, "-o", out, "--model", model, *(["--no-detect"] if i % 5 else [])],
        lambda i: ".npz",
        lambda out: load_triplane(out),
        "encode",
    )
    print(f"photo fuzz: {sum(outcomes.values())} cases, {dict(outcomes)}")
    assert outcomes["ok"] > 20 and outcomes["error"] > 20, outcomes  # both ways out are exercised


def test_fuzz_videos_through_video(capsys, model, tmp_path) -> None:
    """Damaged mp4 and GIF videos: a clean error or a video that decodes."""
    seeds = {
        "clip.mp4": write_mp4(tmp_path / "seed.mp4", frames(6, 32)).read_bytes(),
        "clip.gif": write_gif(tmp_path / "seed.gif", frames(4, 32)).read_bytes(),
    }
    for p in (tmp_path / "seed.mp4", tmp_path / "seed.gif"):
        p.unlink()

    def valid(out: Path) -> None:
        assert decoded_frames(out) >= 1

    outcomes = fuzz(
        capsys,
        tmp_path,
        seeds,
        VIDEO_CASES,
        lambda src, out, i: [
            "video",
            src,
            "-o",
            out,
            "--model",
            model,
            "--max-frames",
            8,
            *(["--no-detect"] if i % 3 else []),
            *VIDEO_SMALL,
        ],
        lambda i: ".gif" if (i // 2) % 2 else ".mp4",
        valid,
        "video",
    )
    print(f"video fuzz: {sum(outcomes.values())} cases, {dict(outcomes)}")
    assert outcomes["ok"] > 5 and outcomes["error"] > 5, outcomes
