"""Names that are not UTF-8 and strings that would drive the terminal: one decoding policy for names
(``lp3d.errors.safe_text``: ``os.fsdecode``, undecodable bytes as ``\\xNN``) and one sanitiser for
every string that came from a file or the command line before it is printed, stored or embedded.
Each test failed before: a triplane every reader refused, a share page blamed on the triplane, escape
sequences and forged lines on the terminal."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane import TriplaneError
from lp3d.render.triplane_io import load_triplane, save_triplane
from support.cli import run

#: A file name byte that is not UTF-8, as Python holds it (``os.fsdecode``: a lone surrogate).
BAD_BYTE = os.fsdecode(b"\xff")
#: What a hostile file might hold: a screen clear, a forged output line, a bidi override.
HOSTILE = "\x1b[2J\x1b]0;owned\x07\nfile:           forged.npz\u202e"


def test_safe_text_escapes_controls_and_undecodable_bytes_and_keeps_text() -> None:
    from lp3d.errors import safe_text

    assert safe_text(f"face{BAD_BYTE}.png") == "face\\xff.png"
    assert safe_text(Path(os.fsdecode(b"a\xfe\xff"))) == "a\\xfe\\xff"
    assert safe_text(b"caf\xc3\xa9 \xff") == "café \\xff"
    assert safe_text(HOSTILE) == "\\x1b[2J\\x1b]0;owned\\x07\\nfile:           forged.npz\\u202e"
    assert safe_text("Zoë ²³ 頭 ✓") == "Zoë ²³ 頭 ✓"


def test_a_source_that_is_not_text_cannot_be_stored(tmp_path) -> None:
    tri = coloured_sphere(size=8)
    with pytest.raises(TriplaneError, match="source: holds a lone surrogate"):
        dataclasses.replace(tri, source=f"lp3d encode face{BAD_BYTE}.png")
    assert not list(tmp_path.iterdir())


@pytest.fixture(scope="module")
def package(tmp_path_factory) -> Path:
    from support.tiny_model import tiny_onnx_package

    return tiny_onnx_package(tmp_path_factory.mktemp("model"))[0]


def test_encode_of_a_photo_whose_name_is_not_utf8_writes_a_readable_triplane(
    capsys, package, tmp_path
) -> None:
    photo = tmp_path / f"face{BAD_BYTE}.png"
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (96, 96, 3), dtype=np.uint8)).save(photo)
    out = tmp_path / "head.npz"
    code, stdout, err = run(capsys, "encode", photo, "-o", out, "--model", package, "--no-detect")
    assert code == 0, err
    tri = load_triplane(out)  # every reader accepts what was written
    assert tri.source is not None and "face\\xff.png" in tri.source, tri.source
    assert BAD_BYTE not in stdout + err


def test_share_of_a_file_and_a_title_that_are_not_utf8(capsys, gpu, tmp_path) -> None:
    src = tmp_path / f"head{BAD_BYTE}.npz"
    save_triplane(src, coloured_sphere(size=8))
    page = tmp_path / "page.html"
    code, _, err = run(capsys, "share", src, "-o", page)
    assert code == 0, err
    assert "head\\xff.npz" in page.read_text(encoding="utf-8")
    code, _, err = run(capsys, "share", src, "-o", page, "--title", f"my{BAD_BYTE} head\x1b[2J")
    assert code == 0, err
    text = page.read_text(encoding="utf-8")
    assert "my\\xff head\\x1b[2J" in text and "\x1b" not in text


def test_info_escapes_what_the_file_says(capsys, tmp_path) -> None:
    path = tmp_path / "hostile.npz"
    save_triplane(path, dataclasses.replace(coloured_sphere(size=8), source=HOSTILE))
    code, stdout, err = run(capsys, "info", path)
    assert code == 0, err
    assert "\x1b" not in stdout and "\u202e" not in stdout and "\x07" not in stdout
    assert [line for line in stdout.splitlines() if line.startswith("file:")] == [
        line for line in stdout.splitlines() if "hostile.npz" in line and line.startswith("file:")
    ]
    assert "source:         \\x1b[2J" in stdout
    code, stdout, _ = run(capsys, "info", path, "--json")
    assert code == 0 and "\x1b" not in stdout and "\u202e" not in stdout


def test_names_in_messages_and_results_are_escaped(capsys, gpu, tmp_path) -> None:
    missing = tmp_path / "gone\x1b[31m\nlp3d: ok.npz"
    code, _, err = run(capsys, "info", missing)
    assert code == 1 and "\x1b" not in err and len(err.strip().splitlines()) == 1, err
    src = tmp_path / "sphere.npz"
    save_triplane(src, coloured_sphere(size=8))
    out = tmp_path / "view\x1b[2J\n.png"
    code, stdout, err = run(capsys, "render", src, "-o", out, "--resolution", "8", "--samples", "4+4")
    assert code == 0 and out.exists(), err
    assert "\x1b" not in stdout and "view\\x1b[2J\\n.png" in stdout, stdout
