"""``lp3d video`` (every frame lifted, ``--steady``, ``--refine``, bad inputs, no faces) and
``lp3d demo`` (the teacher portrait and the astronaut, with and without ``--refine``), with the
video helpers they use."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.render.triplane_io import load_triplane
from support.cli import SMALL, listing, run


@pytest.fixture(scope="module")
def face_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four 160² frames of a slowly panning face."""
    import cv2
    import imageio_ffmpeg
    from skimage.data import astronaut

    path = tmp_path_factory.mktemp("video") / "in.mp4"
    face = astronaut()[:320, 60:380]
    writer = imageio_ffmpeg.write_frames(
        str(path), (160, 160), fps=10, macro_block_size=2, ffmpeg_log_level="error"
    )
    writer.send(None)
    for i in range(4):
        frame = cv2.warpAffine(face, np.float32([[0.5, 0, -2 * i], [0, 0.5, 0]]), (160, 160))
        writer.send(np.ascontiguousarray(frame).tobytes())
    writer.close()
    return path


def test_video_lifts_every_frame(capsys, model, face_video, tmp_path) -> None:
    import imageio_ffmpeg

    out = tmp_path / "out.mp4"
    code, stdout, err = run(
        capsys,
        "video",
        face_video,
        "-o",
        out,
        "--yaw",
        20,
        "--smooth",
        0.5,
        "--model",
        model["onnx"],
        "--side-by-side",
        *SMALL,
    )
    assert code == 0, err
    assert "lifted 4 frames" in stdout and "video" in err  # summary and progress bar
    reader = imageio_ffmpeg.read_frames(str(out))
    assert next(reader)["size"] == (64, 32) and sum(1 for _ in reader) == 4


def test_video_gif_no_detect_and_bad_inputs(capsys, model, face_video, photos, tmp_path) -> None:
    code, _, err = run(
        capsys,
        "video",
        face_video,
        "-o",
        tmp_path / "o.gif",
        "--no-detect",
        "--max-frames",
        2,
        "--model",
        model["onnx"],
        *SMALL,
    )
    assert code == 0, err
    code, _, err = run(
        capsys, "video", photos["text"], "-o", tmp_path / "x.mp4", "--model", model["onnx"], *SMALL
    )
    assert code == 1 and "cannot read as a video" in err
    code, _, err = run(capsys, "video", face_video, "-o", tmp_path / "x.avi", "--model", model["onnx"])
    assert code == 1 and "unsupported format" in err
    code, _, err = run(capsys, "video", face_video, "-o", tmp_path / "x.mp4", "--smooth", 1.0)
    assert code == 2
    for bad in ("-1", "nan", "1e9"):
        code, _, err = run(capsys, "video", face_video, "-o", tmp_path / "x.mp4", "--steady", bad)
        assert code == 2 and "--steady" in err
    assert listing(tmp_path) == {"o.gif"}


def test_video_steady_keeps_every_frame_and_changes_them(capsys, model, face_video, tmp_path) -> None:
    """``--steady`` holds frames back until their window is whole, then flushes: the same
    frames come out, in order, and (σ large against 4 frames) nearer to each other than without it."""
    import imageio_ffmpeg

    outs = {}
    for sigma in ("0", "30"):
        out = tmp_path / f"steady{sigma}.mp4"
        code, stdout, err = run(
            capsys, "video", face_video, "-o", out, "--steady", sigma, "--model", model["onnx"], *SMALL
        )
        assert code == 0, err
        assert "lifted 4 frames" in stdout
        reader = imageio_ffmpeg.read_frames(str(out))
        w, h = next(reader)["size"]
        outs[sigma] = np.stack([np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]).astype(float)
    assert outs["0"].shape == outs["30"].shape and outs["0"].shape[0] == 4
    change = {k: np.abs(np.diff(v, axis=0)).mean() for k, v in outs.items()}
    assert change["30"] < change["0"], change


def test_video_refine_and_flip_average_change_every_frame(capsys, model, face_video, tmp_path) -> None:
    """``lp3d video --refine 1``: each frame's head is fitted to its crop (the camera searched
    for on the first frame, then followed), so the frames differ from plain lifting; so do
    ``--flip-average``'s (each frame encoded with its mirror image)."""
    import imageio_ffmpeg

    frames = {}
    for name, extra in (("plain", ()), ("refined", ("--refine", 1)), ("flipped", ("--flip-average",))):
        out = tmp_path / f"{name}.mp4"
        code, stdout, err = run(
            capsys,
            "video",
            face_video,
            "-o",
            out,
            "--model",
            model["onnx"],
            "--max-frames",
            2,
            "--steady",
            0,
            *SMALL,
            *extra,
        )
        assert code == 0, err
        reader = imageio_ffmpeg.read_frames(str(out))
        w, h = next(reader)["size"]
        frames[name] = np.stack([np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]).astype(float)
    for name in ("refined", "flipped"):
        assert frames["plain"].shape == frames[name].shape and frames["plain"].shape[0] == 2
        assert np.abs(frames["plain"] - frames[name]).mean() > 0.1, name


def test_video_without_faces(capsys, model, tmp_path) -> None:
    import imageio_ffmpeg

    src = tmp_path / "noise.mp4"
    writer = imageio_ffmpeg.write_frames(
        str(src), (64, 64), fps=5, macro_block_size=2, ffmpeg_log_level="error"
    )
    writer.send(None)
    for _ in range(2):
        writer.send(np.full((64, 64, 3), 128, np.uint8).tobytes())
    writer.close()
    code, _, err = run(capsys, "video", src, "-o", tmp_path / "o.mp4", "--model", model["onnx"], *SMALL)
    assert code == 1 and "no face found" in err and "--no-detect" in err
    assert listing(tmp_path) == {"noise.mp4"}


# =============================================================================================== demo


DEMO_SMALL = ("--resolution", 16, "--samples", "4+4", "--frames", 2)


def test_demo_lifts_a_teacher_portrait_and_the_astronaut(capsys, model, tmp_path) -> None:
    out_dir = tmp_path / "demo"
    code, out, err = run(capsys, "demo", "--out", out_dir, "--model", model["onnx"], *DEMO_SMALL)
    assert code == 0, err
    names = ("teacher_portrait", "astronaut")
    expected = {f"{n}{ext}" for n in names for ext in (".npz", ".html", ".crop.png")} | {
        "side_by_side.png",
        "orbit.gif",
    }
    assert listing(out_dir) == expected
    assert (
        "scikit-image astronaut: 512x512, face" in out
    )  # the astronaut's face was detected, not centre-cropped
    for n in names:
        tri = load_triplane(out_dir / f"{n}.npz")
        assert tri.planes.shape == (3, 32, 64, 64) and "lp3d demo" in (tri.source or "")
        assert np.asarray(Image.open(out_dir / f"{n}.crop.png")).shape == (128, 128, 3)
    gif = Image.open(out_dir / "orbit.gif")
    assert gif.n_frames == 2 and gif.size == (2 * 16, 16)  # both heads side by side
    sheet = np.asarray(Image.open(out_dir / "side_by_side.png"))
    assert sheet.shape[0] > 3 * 16  # student rows and the teacher's own views


def test_demo_refine_adds_refined_heads_and_rows(capsys, model, tmp_path) -> None:
    """``lp3d demo --refine 2``: the refined triplanes beside the feed-forward ones, and
    one more row per head in the contact sheet; with ``--flip-average`` the feed-forward heads are
    the flip-averaged ones."""
    plain, refined = tmp_path / "plain", tmp_path / "refined"
    assert run(capsys, "demo", "--out", plain, "--model", model["onnx"], *DEMO_SMALL)[0] == 0
    code, out, err = run(
        capsys,
        "demo",
        "--out",
        refined,
        "--model",
        model["onnx"],
        *DEMO_SMALL,
        "--refine",
        2,
        "--flip-average",
    )
    assert code == 0, err
    assert "teacher_portrait: refined 2 steps" in out and "astronaut: refined 2 steps" in out
    assert {"teacher_portrait.refined.npz", "astronaut.refined.npz"} <= listing(refined)
    a, b = load_triplane(refined / "astronaut.npz"), load_triplane(refined / "astronaut.refined.npz")
    assert "refined 2 steps" in (b.source or "") and not np.array_equal(a.planes, b.planes)
    assert "flip-averaged" in (a.source or "") and "flip-averaged" in out
    assert not np.allclose(a.planes, load_triplane(plain / "astronaut.npz").planes, atol=1e-3)
    rows = {d: np.asarray(Image.open(d / "side_by_side.png")).shape[0] for d in (plain, refined)}
    assert rows[refined] > rows[plain]


def test_demo_with_the_shipped_model(capsys, tmp_path) -> None:
    """``lp3d demo`` as the README runs it (default model), at a small size."""
    code, out, err = run(capsys, "demo", "--out", tmp_path / "demo", *DEMO_SMALL)
    assert code == 0, err
    assert "small.onnx" in out and "config 'small-colour'" in out
    written = listing(tmp_path / "demo")
    assert {"teacher_portrait.npz", "astronaut.npz", "side_by_side.png", "orbit.gif"} <= written
    # The shipped model's 64² head as a web page (lp3d share): within the 3 MB.
    assert (tmp_path / "demo" / "teacher_portrait.html").stat().st_size <= 3_000_000


def test_demo_without_a_model_says_what_to_do(capsys, tmp_path, monkeypatch) -> None:
    import lp3d.lift.inference

    monkeypatch.setattr(lp3d.lift.inference, "DEFAULT_MODEL", tmp_path / "models" / "small.onnx")
    code, _, err = run(capsys, "demo", "--out", tmp_path / "demo", *DEMO_SMALL)
    assert code == 1 and "--model" in err and "python -m lp3d.train" in err
    assert not (tmp_path / "demo").exists()


def test_demo_refuses_an_output_folder_that_is_a_file_before_any_work(capsys, tmp_path) -> None:
    """It once lifted and rendered both portraits (about 20 s) before "File exists"."""
    taken = tmp_path / "demo_out"
    taken.write_text("a file")
    code, out, err = run(capsys, "demo", "--out", taken, *DEMO_SMALL)
    assert code == 1 and err.strip() == f"lp3d demo: error: --out {taken}: is a file, not a folder", err
    assert "model:" not in out and taken.read_text() == "a file"


def test_video_helpers() -> None:
    from lp3d.photo import Crop
    from lp3d.photo.video import nearest_hits, smooth_crops

    np.testing.assert_array_equal(nearest_hits(np.array([2, 5, 9]), 11), [2, 2, 2, 2, 5, 5, 5, 5, 9, 9, 9])
    crops = [Crop(10.0, 10.0, 50.0), Crop(20.0, 10.0, 50.0), Crop(10.0, 10.0, 50.0)]
    smooth = smooth_crops(crops, 0.5)
    assert 10.0 < smooth[0].cx < smooth[1].cx < 20.0 and smooth[1].side == 50.0
