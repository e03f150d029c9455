"""The super-resolution network in the model package: ONNX export and its parity
with torch, the sidecar's ``superres`` entry and its validation, the Python API (features in, image
out, both backends) and the CLI's super-resolved and ``--raw`` outputs (``test_superres_fit.py`` has
the fitting of networks).

Networks are tiny and randomly initialised (weights perturbed so that every layer matters); renders
are 16²-64² with few samples, so the file runs in about a minute on two cores.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from lp3d.cli import main
from lp3d.export.package import (
    check_superres_onnx,
    export_superres,
    package_superres,
)
from lp3d.lift.inference import load_superres, superresolve
from lp3d.lift.model_package import (
    ModelPackageError,
    load_model_package,
    set_package_superres,
    superres_path,
)
from lp3d.nets.superres import SUPERRES_CONFIGS, FoldedSuperResolution, SuperresConfig
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane
from lp3d.superres_fit.fit import FitConfig
from support.superres_package import (
    ONNX_TOLERANCE,
    SR_IN,
    SR_OUT,
    cli_sr_config,
    random_sr,
    superres_package,
    weights_file,
)

SAMPLES = ("--samples", "8+8")


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    return superres_package(tmp_path_factory)


# ===================================================================================== ONNX parity


@pytest.mark.parametrize(
    "config",
    [
        SUPERRES_CONFIGS["tiny"],  # the CPU paper recipe's (64² -> 128², one block)
        FitConfig().superres_config(),  # the shipped model's fit (64² -> 256²)
    ],
    ids=["tiny", "fit-default"],
)
def test_superres_onnx_matches_torch(tmp_path, config) -> None:
    """The exported graph (the folded network) against the torch network, on features in [-1, 1]."""
    sr = random_sr(config)
    path = export_superres(sr, tmp_path / "sr.onnx")
    err = check_superres_onnx(sr, path, batch=3)
    print(f"{config.name}: onnxruntime vs torch max abs error {err:.2e}")
    assert err <= ONNX_TOLERANCE
    # The folded torch form is the same function, to float rounding.
    x = torch.rand(2, config.in_channels, config.input_resolution, config.input_resolution) * 2 - 1
    with torch.no_grad():
        ref, folded = sr(x), FoldedSuperResolution(sr)(x)
    assert ref.shape == (2, 3, config.output_resolution, config.output_resolution)
    assert float((ref - folded).abs().max()) <= 1e-4 * float(ref.abs().max())
    with pytest.raises(ValueError, match=r"features must have shape \(B, 32, 64, 64\)"):
        FoldedSuperResolution(sr)(x[..., :32, :32])


def test_export_refuses_a_network_that_disagrees(tmp_path, monkeypatch) -> None:
    """When onnxruntime and torch disagree beyond the tolerance: ParityError, and no file left behind."""
    import lp3d.export.superres
    from lp3d.export.package import ParityError

    monkeypatch.setattr(lp3d.export.superres, "check_superres_onnx", lambda sr, path: 0.5)
    with pytest.raises(ParityError, match="max abs error 0.5 > 0.001"):
        package_superres(random_sr(cli_sr_config()), tmp_path / "m.onnx")
    assert not superres_path(tmp_path / "m.onnx").exists()


# ================================================================================= package and API


def test_package_entry_and_python_api(package) -> None:
    pkg = load_model_package(package["onnx"])
    entry = pkg.superres
    assert entry is not None and entry.path == superres_path(package["onnx"]) and entry.scale == 4
    assert (entry.input_resolution, entry.output_resolution, entry.in_channels) == (SR_IN, SR_OUT, 32)
    assert entry.about is not None and entry.about["source"] == "test"
    assert entry.about["onnx_max_abs_error"] <= ONNX_TOLERANCE
    assert load_model_package(package["plain"]).superres is None
    assert load_superres(package["plain"]) is None

    sr = load_superres(package["onnx"])
    assert sr is not None and sr.backend == "onnx"
    features = np.random.default_rng(0).uniform(-1, 1, (2, 32, SR_IN, SR_IN)).astype(np.float32)
    image = sr(features)
    with torch.no_grad():
        expected = package["sr"](torch.from_numpy(features)).numpy()
    assert image.shape == (2, 3, SR_OUT, SR_OUT) and np.abs(image - expected).max() <= ONNX_TOLERANCE
    assert np.array_equal(sr(features[0]), image[0])  # one image without a batch axis
    assert np.array_equal(superresolve(features, model=package["onnx"]), image)
    with pytest.raises(ModelPackageError, match="no super-resolution network"):
        superresolve(features, model=package["plain"])
    with pytest.raises(ValueError, match=rf"\(B, 32, {SR_IN}, {SR_IN}\).*resolution={SR_IN}"):
        sr(features[:, :, :8, :8])
    with pytest.raises(ValueError, match="NaN"):
        sr(np.full((1, 32, SR_IN, SR_IN), np.nan, np.float32))
    # The network belongs to the package's decoder and bounds.
    sphere = coloured_sphere(size=8)
    assert sr.accepts(sphere)
    other = coloured_sphere(size=8)
    assert not sr.accepts(dataclasses.replace(other, w1=other.w1 * 1.01))
    assert not sr.accepts(coloured_sphere(size=8, box_warp=1.5))


def test_torch_backend_reads_the_network_from_weights(package, tmp_path) -> None:
    """``lp3d export --weights`` files carry the network for ``--backend torch``; same images."""
    from lp3d.export.superres import superres_weights

    weights = tmp_path / "tiny.pt"
    data = weights_file(package["encoder"], weights)
    assert load_superres(weights) is None
    torch.save({**data, "superres": superres_weights(package["sr"])}, weights)
    sr_torch, sr_onnx = load_superres(weights), load_superres(package["onnx"])
    assert sr_torch is not None and sr_onnx is not None and sr_torch.backend == "torch"
    features = np.random.default_rng(1).uniform(-1, 1, (1, 32, SR_IN, SR_IN)).astype(np.float32)
    assert np.abs(sr_torch(features) - sr_onnx(features)).max() <= ONNX_TOLERANCE
    torch.save({**data, "superres": {"config": {"nope": 1}, "state": {}}}, weights)
    with pytest.raises(ModelPackageError, match="super-resolution configuration cannot be read"):
        load_superres(weights)


def _edited(package: dict[str, object], tmp_path: Path, edit) -> Path:
    """A copy of the SR package whose sidecar's ``superres`` entry went through ``edit``."""
    folder = tmp_path / "edited"
    shutil.copytree(Path(package["onnx"]).parent, folder)
    side = folder / "tiny.json"
    data = json.loads(side.read_text())
    edit(data["superres"]) if "superres" in data else None
    side.write_text(json.dumps(data))
    return folder / "tiny.onnx"


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda e: e.pop("model"), "missing field 'superres.model'"),
        (lambda e: e.update(model="../x.onnx"), "'superres.model' must be an .onnx file name"),
        (lambda e: e.update(model="x.bin"), "'superres.model' must be an .onnx file name"),
        (lambda e: e.update(input_resolution="16"), "'superres.input_resolution' has the wrong type"),
        (lambda e: e.update(input_resolution=True), "'superres.input_resolution' has the wrong type"),
        (lambda e: e.update(output_resolution=48), "'superres.output_resolution' (48) must be"),
        (lambda e: e.update(output_resolution=16), "'superres.output_resolution' (16) must be"),
        (lambda e: e.update(in_channels=3), "'superres.in_channels' must be 32"),
        (lambda e: e.update(sha256="abc"), "'superres.sha256' must be 64 lowercase hex"),
        (lambda e: e.pop("sha256"), "missing field 'superres.sha256'"),
        (lambda e: e.update(about=[1]), "'superres.about' must be an object"),
        (lambda e: e.pop("weights"), "missing field 'superres.weights'"),
        (lambda e: e.update(weights="sub/x.npz"), "'superres.weights' must be an .npz file name"),
        (lambda e: e.update(weights_sha256="0" * 63), "'superres.weights_sha256' must be 64 lowercase hex"),
    ],
)
def test_package_rejects_a_bad_superres_entry(package, tmp_path, edit, words) -> None:
    path = _edited(package, tmp_path, edit)
    with pytest.raises(ModelPackageError, match=words.replace("(", r"\(").replace(")", r"\)")) as info:
        load_model_package(path)
    assert "tiny.json" in str(info.value)


def test_package_rejects_a_superres_entry_that_is_not_an_object(package, tmp_path) -> None:
    folder = tmp_path / "edited"
    shutil.copytree(Path(package["onnx"]).parent, folder)
    side = folder / "tiny.json"
    side.write_text(json.dumps({**json.loads(side.read_text()), "superres": "tiny.superres.onnx"}))
    with pytest.raises(ModelPackageError, match="field 'superres' must be an object"):
        load_model_package(side)


def test_superres_file_missing_altered_or_of_another_shape(package, tmp_path) -> None:
    path = _edited(package, tmp_path, lambda e: None)
    sr_file = superres_path(path)
    data = sr_file.read_bytes()
    sr_file.unlink()
    with pytest.raises(ModelPackageError, match="tiny.superres.onnx: no such file.*'superres.model'"):
        load_superres(path)
    sr_file.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(ModelPackageError, match="'superres.sha256'"):
        load_superres(path)
    # A network of another size under a correct checksum: the graph's shapes are checked too.
    other = random_sr(SuperresConfig(name="o", input_resolution=8, output_resolution=16, block_channels=(4,)))
    export_superres(other, sr_file)
    entry = json.loads(path.with_suffix(".json").read_text())["superres"]
    entry["sha256"] = __import__("hashlib").sha256(sr_file.read_bytes()).hexdigest()
    set_package_superres(path, entry)
    with pytest.raises(ModelPackageError, match=r"input has shape \['batch', 32, 8, 8\].*\(B, 32, 16, 16\)"):
        load_superres(path)
    # Removing the entry leaves a package without a network.
    set_package_superres(path, None)
    assert load_model_package(path).superres is None and load_superres(path) is None


def test_the_weights_file_is_the_exported_network(package, tmp_path) -> None:
    """Export writes MODEL.superres.npz beside the ONNX graph: the folded network's arrays, which the
    renderer's reader loads (no torch, no onnx) into the same network as the graph's (equal images on
    the GPU), and whose checksum the package checks."""
    from lp3d.lift.gpu_superres import gpu_superres, load_gpu_superres
    from lp3d.render.native import renderer

    pkg = load_model_package(package["onnx"])
    entry = pkg.superres
    assert entry is not None and entry.weights_path == superres_path(package["onnx"]).with_suffix(".npz")
    with np.load(entry.weights_path) as f:
        assert sorted(f.files) == sorted(
            ["format_version", "input_resolution"]
            + [f"{k}_{i}" for k in ("convs_up", "biases_up", "convs", "biases", "rgb_weights", "rgb_biases")
               for i in range(2)]
        )  # fmt: skip
        assert int(f["input_resolution"]) == SR_IN and f["convs_0"].dtype == np.float32
    from_file = load_gpu_superres(package["onnx"])
    from_torch = gpu_superres(FoldedSuperResolution(package["sr"]))
    features = np.random.default_rng(3).uniform(-1, 1, (2, 32, SR_IN, SR_IN)).astype(np.float32)
    np.testing.assert_array_equal(from_file.apply(features), from_torch.apply(features))
    direct = renderer().SuperRes.load(entry.weights_path)
    assert (direct.input_resolution, direct.output_resolution) == (SR_IN, SR_OUT)

    path = _edited(package, tmp_path, lambda e: None)
    weights = path.with_name("tiny.superres.npz")
    data = weights.read_bytes()
    weights.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(ModelPackageError, match="'superres.weights_sha256'"):
        load_gpu_superres(path)
    weights.unlink()
    with pytest.raises(ModelPackageError, match="tiny.superres.npz: no such file.*'superres.weights'"):
        load_gpu_superres(path)
    # A file that is not a weights file, under a correct checksum: the reader names it and the key.
    np.savez(weights, format_version=np.array(1), input_resolution=np.array(SR_IN))
    entry_json = json.loads(path.with_suffix(".json").read_text())["superres"]
    entry_json["weights_sha256"] = __import__("hashlib").sha256(weights.read_bytes()).hexdigest()
    set_package_superres(path, entry_json)
    with pytest.raises(ValueError, match="tiny.superres.npz.*expected format_version, input_resolution"):
        load_gpu_superres(path)


# ============================================================================================= CLI


def _size(path: Path) -> tuple[int, int]:
    return Image.open(path).size


def test_render_is_super_resolved_unless_raw(capsys, package, tmp_path) -> None:
    sphere, model = package["sphere"], package["onnx"]
    code, out, err = run(capsys, "render", sphere, "-o", tmp_path / "sr.png", "--model", model, *SAMPLES)
    assert code == 0, err
    assert _size(tmp_path / "sr.png") == (SR_OUT, SR_OUT)
    assert f"{SR_IN}² raw -> {SR_OUT}²" in out and "super-resolved by tiny.superres.onnx" in out
    code, out, err = run(
        capsys, "render", sphere, "-o", tmp_path / "raw.png", "--model", model, "--raw", *SAMPLES
    )
    assert code == 0, err
    assert _size(tmp_path / "raw.png") == (256, 256) and "raw volume render (--raw)" in out
    # --resolution sets the output size either way (the SR image is resized), --depth follows it.
    code, out, err = run(
        capsys,
        "render",
        sphere,
        "-o",
        tmp_path / "r24.png",
        "--model",
        model,
        "--resolution",
        24,
        "--depth",
        tmp_path / "d24.png",
        *SAMPLES,
    )
    assert code == 0, err
    assert _size(tmp_path / "r24.png") == _size(tmp_path / "d24.png") == (24, 24)
    assert "resized to 24²" in out
    # The image is the network's output for the raw features.
    code, _, err = run(
        capsys,
        "render",
        sphere,
        "-o",
        tmp_path / "f.png",
        "--model",
        model,
        "--raw",
        "--features-channel",
        0,
        "--resolution",
        SR_IN,
        *SAMPLES,
    )
    assert code == 0, err


def test_render_image_is_the_network_applied_to_the_raw_features(capsys, package, tmp_path) -> None:
    import lp3d_render
    from lp3d.images import rgb_to_uint8
    from lp3d.render.camera import look_at_camera
    from lp3d.render.native import native_triplane
    from lp3d.render.triplane_io import load_triplane

    code, _, err = run(
        capsys, "render", package["sphere"], "-o", tmp_path / "sr.png", "--model", package["onnx"], *SAMPLES
    )
    assert code == 0, err
    raw = lp3d_render.render(
        native_triplane(load_triplane(package["sphere"])),
        look_at_camera(),
        resolution=SR_IN,
        depth_resolution=8,
        depth_resolution_importance=8,
        outputs=["features"],
    )["features"]
    sr = load_superres(package["onnx"])
    assert sr is not None
    expected = rgb_to_uint8(sr(raw))
    assert np.array_equal(np.asarray(Image.open(tmp_path / "sr.png")), expected)


def test_render_default_uses_the_shipped_models_network_for_its_triplanes(
    capsys, package, tmp_path, monkeypatch
) -> None:
    import lp3d.lift.inference

    monkeypatch.setattr(lp3d.lift.inference, "DEFAULT_MODEL", Path(package["onnx"]))
    code, out, err = run(capsys, "render", package["sphere"], "-o", tmp_path / "a.png", *SAMPLES)
    assert code == 0, err
    assert _size(tmp_path / "a.png") == (SR_OUT, SR_OUT) and "the shipped model's" in out
    # A triplane with another decoder: no network applies; the output says why.
    other = coloured_sphere(size=16)
    save_triplane(tmp_path / "other.npz", dataclasses.replace(other, b1=other.b1 + 0.01))
    code, out, err = run(capsys, "render", tmp_path / "other.npz", "-o", tmp_path / "b.png", *SAMPLES)
    assert code == 0, err
    assert _size(tmp_path / "b.png") == (256, 256) and "decoder is not the shipped model's" in out
    # ... and asking for a package's network for it is an error.
    code, _, err = run(
        capsys, "render", tmp_path / "other.npz", "-o", tmp_path / "c.png", "--model", package["onnx"]
    )
    assert code == 1 and "--raw" in err and "decoder" in err and not (tmp_path / "c.png").exists()
    # A shipped model without a network: raw, said so.
    monkeypatch.setattr(lp3d.lift.inference, "DEFAULT_MODEL", Path(package["plain"]))
    code, out, err = run(capsys, "render", package["sphere"], "-o", tmp_path / "d.png", *SAMPLES)
    assert code == 0 and "has no super-resolution network" in out
    code, _, err = run(
        capsys, "render", package["sphere"], "-o", tmp_path / "e.png", "--model", package["plain"]
    )
    assert code == 1 and "has no super-resolution network" in err


def test_orbit_writes_super_resolved_frames(capsys, package, tmp_path) -> None:
    sphere, model = package["sphere"], package["onnx"]
    code, out, err = run(
        capsys, "orbit", sphere, "-o", tmp_path / "o.gif", "--model", model, "--frames", 3, *SAMPLES
    )
    assert code == 0, err
    gif = Image.open(tmp_path / "o.gif")
    assert gif.n_frames == 3 and gif.size == (SR_OUT, SR_OUT)
    assert "super-resolved" in out and "orbit" in err  # the progress bar
    code, out, err = run(
        capsys,
        "orbit",
        sphere,
        "-o",
        tmp_path / "r.gif",
        "--model",
        model,
        "--raw",
        "--frames",
        2,
        "--resolution",
        20,
        *SAMPLES,
    )
    assert code == 0, err
    assert Image.open(tmp_path / "r.gif").size == (20, 20) and "raw volume render (--raw)" in out


def test_video_and_demo_use_the_models_network(capsys, package, tmp_path) -> None:
    import imageio_ffmpeg

    src = tmp_path / "in.mp4"
    writer = imageio_ffmpeg.write_frames(
        str(src), (48, 48), fps=5, macro_block_size=2, ffmpeg_log_level="error"
    )
    writer.send(None)
    for i in range(2):
        writer.send(np.full((48, 48, 3), 60 + 40 * i, np.uint8).tobytes())
    writer.close()
    common = ("--no-detect", "--model", package["onnx"], *SAMPLES)
    code, out, err = run(capsys, "video", src, "-o", tmp_path / "sr.gif", *common)
    assert code == 0, err
    assert Image.open(tmp_path / "sr.gif").size == (SR_OUT, SR_OUT) and "super-resolved" in out
    code, out, err = run(
        capsys,
        "video",
        src,
        "-o",
        tmp_path / "raw.gif",
        "--raw",
        "--resolution",
        16,
        "--side-by-side",
        *common,
    )
    assert code == 0, err
    assert Image.open(tmp_path / "raw.gif").size == (32, 16)

    code, out, err = run(
        capsys,
        "demo",
        "--out",
        tmp_path / "demo",
        "--model",
        package["onnx"],
        "--samples",
        "4+4",
        "--frames",
        2,
    )
    assert code == 0, err
    assert Image.open(tmp_path / "demo" / "orbit.gif").size == (2 * SR_OUT, SR_OUT)
    assert f"{SR_IN}² raw -> {SR_OUT}²" in out
