"""``lp3d eval-photos``: real photos lifted, their novel views scored by dlib's face recognition
(lp3d.evaluation.photos), with the shipped model on the astronaut at a small render size."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.cli import main


@pytest.fixture(scope="module")
def photos(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from skimage.data import astronaut

    folder = tmp_path_factory.mktemp("photos")
    Image.fromarray(astronaut()).save(folder / "astronaut.png")
    return folder


def test_eval_photos_scores_every_view(capsys, photos, tmp_path) -> None:
    out = tmp_path / "report"
    argv = ["eval-photos", photos, "--out", out, "--yaws", "0,20", "--samples", "12+12", "--refine", "3"]
    assert main([str(a) for a in argv]) == 0
    stdout = capsys.readouterr().out
    assert "astronaut.png: camera yaw" in stdout and "| ±20° |" in stdout
    report = json.loads((out / "report.json").read_text())
    assert report["refine_steps"] == 3 and report["summary"]["photos"] == 1
    (photo,) = report["photos"]
    assert [v["yaw_deg"] for v in photo["views"]] == [0.0, 20.0]
    for v in photo["views"]:
        if v["face_found"]:
            assert 0.0 < v["distance"] < 2.0 and -1.0 <= v["cosine"] <= 1.0
            assert v["recognised"] == (v["distance"] < 0.6)
    assert np.isfinite(photo["input_view"]["face_psnr_db"]) and 0 < photo["input_view"]["face_ssim"] <= 1
    # A head, not a card: the face stands out of the head by some hundredths of the scene, encoded or
    # refined (a flat card would give 0).
    relief = photo["depth_relief"]
    assert 0.005 < relief["encoder"] < 0.5 and 0.0 <= relief["head"] < 0.5
    assert report["summary"]["depth_relief_ratio"] == pytest.approx(relief["head"] / relief["encoder"])
    sheet = np.asarray(Image.open(out / "identity.png"))
    assert sheet.shape[1] == 3 * 256 and sheet.shape[0] == 256 + 14  # photo + two views, captioned


def test_eval_photos_refuses_bad_arguments(capsys, photos, tmp_path) -> None:
    (tmp_path / "taken").mkdir()
    assert main(["eval-photos", str(photos), "--out", str(tmp_path / "taken")]) == 1
    assert "exists" in capsys.readouterr().err
    assert main(["eval-photos", str(photos), "--out", str(tmp_path / "x"), "--yaws", "0,abc"]) == 1
    assert "--yaws" in capsys.readouterr().err
    blank = tmp_path / "blank"
    blank.mkdir()
    Image.fromarray(np.full((200, 200, 3), 90, np.uint8)).save(blank / "wall.png")
    assert main(["eval-photos", str(blank), "--out", str(tmp_path / "y")]) == 1
    err = capsys.readouterr().err
    assert "wall.png: no face found" in err and "no photo could be lifted" in err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_depth_relief_is_the_face_regions_spread() -> None:
    from lp3d.evaluation.photos import depth_relief

    y, x = np.mgrid[0:64, 0:64]
    bump = 2.7 - 0.2 * np.exp(-((x - 32.0) ** 2 + (y - 32.0) ** 2) / 50.0)  # a nose toward the camera
    box = (64, 64, 192, 192)  # in a 256² image's pixels: the middle half of the 64² depth image
    assert depth_relief(bump, box, 256) == pytest.approx(np.ptp(np.percentile(bump[16:48, 16:48], [5, 95])))
    assert 0.1 < depth_relief(bump, box, 256) < 0.2  # most of the 0.2 bump, less its tails
    assert depth_relief(np.full((64, 64), 2.7), box, 256) == 0.0  # a card has no relief
