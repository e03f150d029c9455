"""``lp3d encode``: a photo lifted through the tiny model (ONNX and torch backends, batches,
``--refine``, ``--flip-average``), bad photos and bad models; and the pieces behind it: the model
package, photo loading and alignment.

The encoder is the randomly initialised ``tiny`` configuration exported to ONNX once per session."""

from __future__ import annotations

import json
import os
import shutil
import stat

import numpy as np
import pytest
from PIL import Image

from lp3d.lift.model_package import ModelPackageError, load_model_package, save_model_package
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import load_triplane, save_triplane
from support.cli import listing, run


def test_encode_onnx_single_photo(capsys, model, photos, tmp_path) -> None:
    out = tmp_path / "head.npz"
    code, stdout, err = run(
        capsys, "encode", photos["face"], "-o", out, "--model", model["onnx"], "--save-crop"
    )
    assert code == 0, err
    assert "face" in stdout and "roll" in stdout and "encode" in stdout and "s/image" in stdout
    tri = load_triplane(out)
    pkg = load_model_package(model["onnx"])
    assert tri.planes.shape == (3, 32, 64, 64) and tri.planes.dtype == np.float32
    np.testing.assert_array_equal(tri.w1, pkg.w1)
    assert tri.box_warp == pkg.box_warp and "face.jpg" in (tri.source or "")
    crop = np.asarray(Image.open(tmp_path / "head.crop.png"))
    assert crop.shape == (128, 128, 3)
    assert listing(tmp_path) == {"head.npz", "head.crop.png"}


def test_encode_refine_fits_the_head_to_its_photo(capsys, model, photos, tmp_path) -> None:
    """``--refine N``: N steps of the torch fit after the ONNX encoder; the file records
    them, keeps the package's decoder and differs from the feed-forward planes."""
    plain, refined = tmp_path / "plain.npz", tmp_path / "refined.npz"
    common = ("--model", model["onnx"], "--no-detect")
    code, _, err = run(capsys, "encode", photos["face"], "-o", plain, *common)
    assert code == 0, err
    code, stdout, err = run(capsys, "encode", photos["face"], "-o", refined, *common, "--refine", 2)
    assert code == 0, err
    assert "refined 2 steps" in stdout and "input view" in stdout and "refine" in stdout
    a, b = load_triplane(plain), load_triplane(refined)
    assert "refined 2 steps" in (b.source or "") and b.camera is not None
    np.testing.assert_array_equal(a.w0, b.w0)
    assert not np.array_equal(a.planes, b.planes)
    code, _, err = run(capsys, "encode", photos["face"], "-o", refined, *common, "--refine", -1)
    assert code == 2 and "--refine" in err


def test_encode_flip_average_is_the_mean_of_the_photo_and_its_mirror(capsys, model, photos, tmp_path) -> None:
    """``--flip-average``: the written planes are ``LoadedEncoder.encode(crop, flip_average=True)`` of
    the crop it saved, which differs from the plain encoding (the random encoder is not symmetric)."""
    from lp3d.lift.inference import load_encoder
    from lp3d.photo import to_encoder_input

    plain, flipped = tmp_path / "plain.npz", tmp_path / "flipped.npz"
    common = ("--model", model["onnx"], "--no-detect")
    code, _, err = run(capsys, "encode", photos["face_crop"], "-o", plain, *common)
    assert code == 0, err
    code, stdout, err = run(
        capsys, "encode", photos["face_crop"], "-o", flipped, *common, "--flip-average", "--save-crop"
    )
    assert code == 0, err
    assert "flip-averaged" in stdout
    tri = load_triplane(flipped)
    assert "flip-averaged" in (tri.source or "")
    crop = np.asarray(Image.open(tmp_path / "flipped.crop.png"))
    want = load_encoder(model["onnx"]).encode(to_encoder_input(crop[None]), flip_average=True)[0]
    np.testing.assert_allclose(tri.planes, want, rtol=0, atol=1e-6)
    assert np.abs(tri.planes - load_triplane(plain).planes).max() > 1e-3


def test_encode_and_the_python_api_write_the_same_permissions(capsys, model, photos, tmp_path) -> None:
    """``lp3d encode`` and ``save_triplane`` publish through one writer (lp3d.atomic): the outputs get
    the mode of any new file, ``0666 & ~umask``. The umask 027 is unusual on purpose: its 0640 is
    neither mkstemp's 0600 nor the common 0644."""
    old = os.umask(0o027)
    try:
        out = tmp_path / "cli.npz"
        code, _, err = run(
            capsys,
            "encode",
            photos["face_crop"],
            "-o",
            out,
            "--model",
            model["onnx"],
            "--no-detect",
            "--save-crop",
        )
        assert code == 0, err
        save_triplane(tmp_path / "api.npz", load_triplane(out))
    finally:
        os.umask(old)
    modes = {p.name: oct(stat.S_IMODE(p.stat().st_mode)) for p in tmp_path.iterdir()}
    assert modes == {name: oct(0o640) for name in ("cli.npz", "cli.crop.png", "api.npz")}


def test_encode_folder_batch_and_torch_backends(capsys, model, photos, tmp_path) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    shutil.copy(photos["face"], folder / "a.jpg")
    shutil.copy(photos["face_crop"], folder / "b.png")
    (folder / "readme.txt").write_text("not a photo; ignored by the folder scan")
    outdir = tmp_path / "out"
    code, _, err = run(capsys, "encode", folder, "-o", outdir, "--model", model["onnx"], "--batch-size", 2)
    assert code == 0, err
    assert listing(outdir) == {"a.npz", "b.npz"}
    onnx_planes = load_triplane(outdir / "a.npz").planes
    # Torch, both checkpoint layouts: the same planes as ONNX Runtime.
    for key in ("pt", "train"):
        dest = tmp_path / f"{key}.npz"
        code, stdout, err = run(
            capsys, "encode", folder / "a.jpg", "-o", dest, "--model", model[key], "--half"
        )
        assert code == 0, err
        tri = load_triplane(dest)
        assert tri.planes.dtype == np.float16 and "torch" in stdout
        np.testing.assert_allclose(tri.planes.astype(np.float32), onnx_planes, atol=5e-3, rtol=5e-3)


def test_encode_conversions_and_no_detect(capsys, model, photos, tmp_path) -> None:
    code, _, err = run(capsys, "encode", photos["grey"], "-o", tmp_path / "g.npz", "--model", model["onnx"])
    assert code == 0 and "warning:" in err and "grayscale" in err
    code, _, err = run(capsys, "encode", photos["rgba"], "-o", tmp_path / "r.npz", "--model", model["onnx"])
    assert code == 0 and "alpha" in err
    code, out, err = run(
        capsys, "encode", photos["noise"], "-o", tmp_path / "n.npz", "--model", model["onnx"], "--no-detect"
    )
    assert code == 0 and "no detection" in out, err
    assert listing(tmp_path) == {"g.npz", "r.npz", "n.npz"}


@pytest.mark.parametrize(
    ("photo", "words"),
    [
        ("noface", "--no-detect"),
        ("text", "not an image"),
        ("empty", "empty file"),
        ("truncated", "truncated"),
        ("huge", "MP limit"),
    ],
)
def test_encode_bad_photos(capsys, model, photos, tmp_path, photo, words) -> None:
    code, _, err = run(capsys, "encode", photos[photo], "-o", tmp_path / "x.npz", "--model", model["onnx"])
    assert code == 1 and words in err and err.startswith("lp3d encode: error:"), err
    assert listing(tmp_path) == set()


def test_encode_one_bad_photo_fails_the_batch(capsys, model, photos, tmp_path) -> None:
    outdir = tmp_path / "out"
    code, _, err = run(
        capsys, "encode", photos["face"], photos["noface"], "-o", outdir, "--model", model["onnx"]
    )
    assert code == 1 and "noface.png" in err
    assert listing(tmp_path) == set()  # the output folder it would have created is gone too


def test_encode_large_photo_is_downscaled_for_detection(capsys, model, photos, tmp_path) -> None:
    big = tmp_path / "big.jpg"
    Image.open(photos["face"]).resize((2600, 2600), Image.Resampling.BILINEAR).save(big, quality=85)
    code, out, err = run(capsys, "encode", big, "-o", tmp_path / "big.npz", "--model", model["onnx"])
    assert code == 0, err
    assert "2600x2600, face" in out


def test_encode_model_errors(capsys, model, photos, tmp_path, monkeypatch) -> None:
    import lp3d.lift.inference

    monkeypatch.setattr(lp3d.lift.inference, "DEFAULT_MODEL", tmp_path / "models" / "small.onnx")
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz")
    assert code == 1 and "--model" in err and "python -m lp3d.train" in err
    lone = tmp_path / "lone.onnx"
    shutil.copy(model["onnx"], lone)
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz", "--model", lone)
    assert code == 1 and "sidecar" in err and "lone.json" in err
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"not a protobuf")
    shutil.copy(model["onnx"].with_suffix(".json"), broken.with_suffix(".json"))
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz", "--model", broken)
    assert code == 1 and "cannot load the ONNX model" in err
    import torch

    odd = tmp_path / "odd.pt"
    torch.save({"weights": torch.zeros(3)}, odd)
    code, _, err = run(capsys, "encode", photos["face"], "-o", tmp_path / "x.npz", "--model", odd)
    assert code == 1 and "layout not understood" in err
    code, _, err = run(
        capsys,
        "encode",
        photos["face"],
        photos["face_crop"],
        "-o",
        tmp_path / "x.npz",
        "--model",
        model["onnx"],
    )
    assert code == 1 and "output folder" in err
    code, _, err = run(
        capsys, "encode", photos["face"], "-o", tmp_path / "no" / "x.npz", "--model", model["onnx"]
    )
    assert code == 1 and "does not exist" in err
    assert not list(tmp_path.glob("*.npz"))


# ============================================================================== model package, photo


def test_model_package_round_trip_and_errors(model, tmp_path) -> None:
    pkg = load_model_package(model["onnx"])
    assert load_model_package(model["onnx"].with_suffix(".json")).model_path == model["onnx"]
    assert pkg.image_size == 128 and pkg.triplane_resolution == 64 and pkg.config_name == "tiny"
    tri = coloured_sphere(size=8)
    np.testing.assert_array_equal(pkg.w0, tri.w0)  # JSON round trip is exact
    np.testing.assert_array_equal(pkg.b1, tri.b1)
    data = json.loads(model["onnx"].with_suffix(".json").read_text())
    side = tmp_path / "m.json"
    for change, words in (
        ({"format": "other"}, "not an lp3d model package"),
        ({"format_version": 99}, "format_version 99"),
        ({"decoder": {**data["decoder"], "w0": [[0.0] * 32] * 63}}, "decoder.w0: shape"),
        ({"ray_end": 1.0}, "ray_end"),
        ({"image_size": "big"}, "image_size"),
    ):
        side.write_text(json.dumps({**data, **change}))
        with pytest.raises(ModelPackageError, match=words.replace("(", r"\(")):
            load_model_package(side)
    side.write_text("{ not json")
    with pytest.raises(ModelPackageError, match="unreadable"):
        load_model_package(side)
    with pytest.raises(ModelPackageError, match="shape"):
        save_model_package(tmp_path / "x.onnx", (tri.w0[:5], tri.b0, tri.w1, tri.b1), "tiny", (1, 2, 3))


def test_load_image_modes(tmp_path) -> None:
    from lp3d.photo import load_image

    deep = tmp_path / "deep.png"
    Image.fromarray(np.full((20, 20), 65535, np.uint16)).save(deep)
    rgb, notes = load_image(deep)
    assert rgb.shape == (20, 20, 3) and rgb.max() == 255 and any("grayscale" in n for n in notes)
    pal = tmp_path / "pal.png"
    Image.new("P", (20, 20), 3).save(pal, transparency=0)
    rgb, notes = load_image(pal)
    assert rgb.shape == (20, 20, 3) and any("alpha" in n for n in notes)
    cmyk = tmp_path / "cmyk.jpg"
    Image.new("CMYK", (20, 20), (0, 255, 255, 0)).save(cmyk)
    rgb, notes = load_image(cmyk)
    assert rgb.shape == (20, 20, 3) and rgb[10, 10, 0] > 200 and any("CMYK" in n for n in notes)
    tiny = tmp_path / "tiny.png"
    Image.new("RGB", (8, 8)).save(tiny)
    with pytest.raises(ValueError, match="too small"):
        load_image(tiny)


def test_alignment_levels_a_tilted_face(photos) -> None:
    import cv2

    from lp3d.photo import Crop, detect_face

    face = np.asarray(Image.open(photos["face"]))
    base = detect_face(face)
    assert base is not None
    # Turn the photo 8° counter-clockwise on screen: the face's roll drops by 8°.
    turned = cv2.warpAffine(face, cv2.getRotationMatrix2D((224.0, 113.0), 8.0, 1.0), (512, 512))
    found = detect_face(turned)
    assert found is not None
    assert abs((base.alignment.roll_deg - found.alignment.roll_deg) - 8.0) < 1.5
    # The crop centre maps to the output centre.
    crop = Crop(cx=100.0, cy=50.0, side=40.0, angle_deg=30.0)
    m = crop.matrix(64)
    np.testing.assert_allclose(m @ [100.0, 50.0, 1.0], [31.5, 31.5], atol=1e-9)
