"""Outputs never replace an input or each other. Every ``lp3d`` command that reads files and writes
others refuses, before any work, an output that is an input by another name (the same name, a
relative path, a symlink, a hard link) with a clear error and exit status 1, leaving every file as it
was; so does ``lp3d-view --screenshot`` for its PNG and the JSON sidecar beside it. None of these
refusals needs a GPU or a display."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from PIL import Image

from lp3d.cli import main
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden temporary files included) and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def same_name(folder: Path, target: Path, name: str) -> Path:
    return target


def relative(folder: Path, target: Path, name: str) -> Path:
    (folder / "sub").mkdir(exist_ok=True)
    return Path("sub", "..", target.name)  # the test runs in ``folder``


def symlink(folder: Path, target: Path, name: str) -> Path:
    (folder / name).symlink_to(target)
    return folder / name


def hardlink(folder: Path, target: Path, name: str) -> Path:
    os.link(target, folder / name)
    return folder / name


ALIASES: dict[str, Callable[[Path, Path, str], Path]] = {
    "same name": same_name,
    "relative path": relative,
    "symlink": symlink,
    "hard link": hardlink,
}


@pytest.fixture
def in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(tmp_path)  # relative paths are relative to the test's folder
    return tmp_path


@pytest.mark.parametrize("alias", sorted(ALIASES))
def test_encode_refuses_to_overwrite_its_photo(capsys, in_tmp: Path, alias: str) -> None:
    # A photo that happens to be called selfie.npz: `lp3d encode selfie.npz -o selfie.npz`.
    photo = in_tmp / "selfie.npz"
    Image.new("RGB", (80, 80), (200, 150, 120)).save(photo, format="PNG")
    output = ALIASES[alias](in_tmp, photo, "out.npz")
    before = snapshot(in_tmp)
    code, _, err = run(capsys, "encode", photo, "-o", output, "--no-detect")
    assert code == 1, err
    assert "same file as the photo" in err and "selfie.npz" in err, err
    assert snapshot(in_tmp) == before


def test_encode_crop_may_not_replace_an_input_photo(capsys, in_tmp: Path) -> None:
    # Encoding a folder into itself with --save-crop: x.jpg's crop would be x.crop.png, an input.
    folder = in_tmp / "photos"
    folder.mkdir()
    for name in ("x.jpg", "x.crop.png"):
        Image.new("RGB", (80, 80), (90, 60, 40)).save(folder / name)
    before = snapshot(in_tmp)
    code, _, err = run(capsys, "encode", folder, "-o", folder, "--save-crop", "--no-detect")
    assert code == 1 and "x.crop.png" in err and "same file as the photo" in err, err
    assert snapshot(in_tmp) == before


@pytest.fixture
def triplane(in_tmp: Path) -> Path:
    path = in_tmp / "head.npz"
    save_triplane(path, coloured_sphere(size=8))
    return path


@pytest.mark.parametrize(
    ("command", "name"),
    [("render", "view.png"), ("orbit", "orbit.gif"), ("mesh", "head.ply"), ("share", "head.html")],
)
@pytest.mark.parametrize("alias", ["symlink", "hard link"])
def test_triplane_commands_refuse_an_output_that_is_the_triplane(
    capsys, in_tmp: Path, triplane: Path, command: str, name: str, alias: str
) -> None:
    output = ALIASES[alias](in_tmp, triplane, name)
    before = snapshot(in_tmp)
    code, _, err = run(capsys, command, triplane, "-o", output)
    assert code == 1 and "same file as the triplane" in err, err
    assert snapshot(in_tmp) == before


def test_render_outputs_may_not_be_one_file(capsys, in_tmp: Path, triplane: Path) -> None:
    (in_tmp / "view.png").write_bytes(b"an older render")
    os.link(in_tmp / "view.png", in_tmp / "depth.png")
    before = snapshot(in_tmp)
    for depth in ("view.png", "./view.png", "depth.png"):
        code, _, err = run(capsys, "render", triplane, "-o", "view.png", "--depth", depth)
        assert code == 1 and "name the same file" in err, err
    assert snapshot(in_tmp) == before


@pytest.mark.parametrize("alias", ["same name", "symlink"])
def test_video_refuses_to_overwrite_its_input(capsys, in_tmp: Path, alias: str) -> None:
    video = in_tmp / "talk.mp4"
    video.write_bytes(b"stands in for a video: refused before it is read")
    output = ALIASES[alias](in_tmp, video, "out.mp4")
    code, _, err = run(capsys, "video", video, "-o", output)
    assert code == 1 and "same file as the input video" in err, err
    assert video.read_bytes().startswith(b"stands in")


# ---------------------------------------------------------------------------------------- lp3d-view


def view(*args: object) -> subprocess.CompletedProcess[str]:
    """``lp3d-view ARGS`` without a display: a refusal must come before any window opens."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    cmd = [sys.executable, "-m", "lp3d.cli", "view", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)


@pytest.mark.parametrize(
    ("shot", "words"),
    [
        ("head.npz", "would be replaced"),  # lp3d-view --screenshot v.npz v.npz
        ("./sub/../head.npz", "would be replaced"),
        ("link.png", "would be replaced"),  # a symlink to the triplane
        ("head.png", "sidecar"),  # head.png's sidecar head.json is the triplane below
        ("out.json", "sidecar"),  # the sidecar out.json would replace the screenshot itself
        ("shot.jpg", ".png"),
        ("folder.png", "is a folder"),
        ("missing/shot.png", "does not exist"),
    ],
)
def test_viewer_screenshot_never_replaces_an_input(
    in_tmp: Path, triplane: Path, shot: str, words: str
) -> None:
    (in_tmp / "sub").mkdir()
    (in_tmp / "folder.png").mkdir()
    (in_tmp / "link.png").symlink_to(triplane)
    input_file = triplane
    if shot == "head.png":  # a triplane file named head.json, which head.png's sidecar would replace
        input_file = triplane.rename(in_tmp / "head.json")
    before = snapshot(in_tmp)
    proc = view("--screenshot", shot, input_file)
    assert proc.returncode == 1, proc.stderr
    assert words in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert snapshot(in_tmp) == before


def test_viewer_drag_image_never_replaces_an_input(in_tmp: Path, triplane: Path) -> None:
    """With --drag-frames the screenshot also writes the window during the drag, head.png ->
    head.drag.png: a triplane of that name is refused before any window opens."""
    input_file = triplane.rename(in_tmp / "head.drag.png")
    before = snapshot(in_tmp)
    proc = view("--drag-frames", "3", "--screenshot", "head.png", input_file)
    assert proc.returncode == 1, proc.stderr
    assert "drag image" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert snapshot(in_tmp) == before
