"""Model packages and their makers under hostile use: ``lp3d export`` never destroys a file
it reads or one it wrote (class 2), and a model package from someone else is validated like a triplane
file (class 1): a clear error naming the file, never a traceback, a huge allocation or a silent
mismatch."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import pytest
import torch

from lp3d.cli import main
from support.paths import REPO

# ====================================================================== lp3d export keeps its files


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained tiny-configuration checkpoint (export needs no training) in a run folder."""
    from lp3d.training import TRAIN_CONFIGS, Trainer, build_teacher
    from lp3d.training.losses import build_perceptual

    cfg = TRAIN_CONFIGS["tiny-paper"]
    out = tmp_path_factory.mktemp("run")
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    trainer = Trainer(cfg, out, teacher=teacher, perceptual=build_perceptual("none"), progress=False)
    return Path(trainer.save_checkpoint())


def digests(*paths: Path) -> list[str | None]:
    return [hashlib.sha256(p.read_bytes()).hexdigest() if p.exists() else None for p in paths]


def export(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str]:
    code = main(["export", *(str(a) for a in argv)])
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        # Each of these overwrote the checkpoint (or one output with another) and exited 0.
        (["-o", "{ckpt}"], "-o {ckpt} is the same file as the checkpoint"),
        (["-o", "{tmp}/m.onnx", "--weights", "{ckpt}"], "--weights {ckpt} is the same file as the"),
        (["-o", "{tmp}/m.onnx", "--weights", "{tmp}/m.onnx"], "--weights {tmp}/m.onnx and -o {tmp}/m.onnx"),
        (["-o", "{tmp}/m.onnx", "--weights", "{tmp}/m.json"], "--weights {tmp}/m.json and its sidecar"),
        (["-o", "{tmp}/m.json"], "-o {tmp}/m.json: a model file must not end in .json"),
        (["-o", "{tmp}"], "-o {tmp} is a folder"),
        # A run folder: the checkpoint it resolves to is an input too.
        (["-o", "{ckpt}", "--run-folder"], "-o {ckpt} is the same file as the checkpoint"),
    ],
    ids=["o-ckpt", "weights-ckpt", "o-weights", "weights-sidecar", "json", "folder", "run-folder"],
)
def test_export_never_overwrites_its_input_or_another_output(
    checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], words: str
) -> None:
    source = checkpoint.parent.parent if "--run-folder" in flags else checkpoint
    argv = [f.format(ckpt=checkpoint, tmp=tmp_path) for f in flags if f != "--run-folder"]
    (tmp_path / "m.json").write_text("{}")  # an unrelated file where a sidecar would go
    before = digests(checkpoint, tmp_path / "m.json")
    code, err = export(capsys, source, *argv)
    assert code == 1, err
    assert words.format(ckpt=checkpoint, tmp=tmp_path) in err and "Traceback" not in err
    assert digests(checkpoint, tmp_path / "m.json") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]


def test_a_failed_parity_check_keeps_the_existing_model(
    checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import lp3d.export.package

    out = tmp_path / "model.onnx"
    existing = [out, tmp_path / "model.json", tmp_path / "model.superres.onnx"]
    for i, p in enumerate(existing):
        p.write_bytes(b"a model the user wants to keep %d" % i)
    before = digests(*existing)
    monkeypatch.setattr(lp3d.export.package, "check_onnx", lambda student, path: 0.5)
    code, err = export(capsys, checkpoint, "-o", out, "--no-superres")
    assert code == 1
    assert "max abs error 0.5 > 0.001" in err and f"{out} left as it was" in err
    assert digests(*existing) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in existing)  # no staging left


def test_a_failed_superres_parity_check_keeps_the_existing_network(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import lp3d.export.superres
    from lp3d.export.package import ParityError, package_superres
    from lp3d.nets.superres import SuperresConfig, SuperResolution

    existing = tmp_path / "m.superres.onnx"
    existing.write_bytes(b"the network that passed last time")
    monkeypatch.setattr(lp3d.export.superres, "check_superres_onnx", lambda sr, path: 0.5)
    torch.manual_seed(0)
    sr = SuperResolution(
        SuperresConfig(name="t", input_resolution=8, output_resolution=16, block_channels=(4,), w_dim=4)
    )
    with pytest.raises(ParityError, match="max abs error 0.5 > 0.001"):
        package_superres(sr, tmp_path / "m.onnx")
    assert existing.read_bytes() == b"the network that passed last time"
    assert [p.name for p in tmp_path.iterdir()] == ["m.superres.onnx"]


# ============================================================ a model package is outside input too


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """The tiny stand-in ONNX package, its sidecar as data, and the same encoder as a torch weights
    file (``lp3d export --weights``' layout)."""
    from support.tiny_model import tiny_onnx_package

    folder = tmp_path_factory.mktemp("package")
    onnx_path, enc, tri, bounds = tiny_onnx_package(folder)
    weights = {
        "format": "lp3d-encoder-weights-v1",
        "config": enc.config.to_dict(),
        "encoder": {k: v.detach().clone() for k, v in enc.state_dict().items()},
        "plane_offset": None,
        "decoder": {k: torch.from_numpy(getattr(tri, k).copy()) for k in ("w0", "b0", "w1", "b1")},
        "bounds": bounds,
    }
    sidecar = json.loads(onnx_path.with_suffix(".json").read_text())
    return {"onnx": onnx_path, "sidecar": sidecar, "pt": weights}


def hostile_sidecar(package: dict, folder: Path, text: str) -> Path:
    """A copy of the tiny package whose sidecar is ``text``."""
    onnx_path = folder / "m.onnx"
    shutil.copyfile(package["onnx"], onnx_path)
    onnx_path.with_suffix(".json").write_text(text)
    return onnx_path


def with_fields(package: dict, **change: object) -> str:
    return json.dumps({**package["sidecar"], **change})


NESTED = "[" * 100_000 + "]" * 100_000
SIDECARS = {
    # RecursionError tracebacks.
    "nested-about": (lambda pkg: with_fields(pkg)[:-1] + f', "x": {NESTED}}}', "nested too deeply"),
    "nested-whole": (lambda pkg: NESTED, "nested too deeply"),
    # An int() of 5000 digits raised a bare ValueError naming no file.
    "huge-int": (lambda pkg: with_fields(pkg, image_size=0)[:-1] + ', "y": 1' + "0" * 5000 + "}", "digits"),
    # Claimed sizes, capped before anything is allocated from them (2**31 was a 4 GiB crop).
    "image-size": (lambda pkg: with_fields(pkg, image_size=2**31), "image_size must be in [8, 4096]"),
    "triplane-size": (
        lambda pkg: with_fields(pkg, triplane_resolution=2**40),
        "triplane_resolution must be in [2, 2048], got 1099511627776",
    ),
    # A size the graph does not produce was silently ignored.
    "triplane-mismatch": (
        lambda pkg: with_fields(pkg, triplane_resolution=32),
        "but the package says (B, 3, 32, 32, 32)",
    ),
    # Finite weights whose sums overflow float32: accepted here, refused only at render time.
    "decoder-overflow": (
        lambda pkg: with_fields(pkg, decoder={**pkg["sidecar"]["decoder"], "w0": [[1e37] * 32] * 64}),
        "the decoder overflows float32: on planes up to 1 its values reach",
    ),
}


@pytest.mark.parametrize("case", sorted(SIDECARS))
def test_hostile_sidecars_are_refused_at_load(package, tmp_path, case) -> None:
    from lp3d.lift.inference import load_encoder
    from lp3d.lift.model_package import ModelPackageError

    make, words = SIDECARS[case]
    onnx_path = hostile_sidecar(package, tmp_path, make(package))
    with pytest.raises(ModelPackageError, match=re.escape(words)) as caught:
        load_encoder(onnx_path)
    assert str(onnx_path.parent) in str(caught.value)  # names the file


def test_an_oversized_sidecar_is_refused_before_it_is_read(package, tmp_path) -> None:
    from lp3d.lift.model_package import ModelPackageError, load_model_package

    onnx_path = hostile_sidecar(package, tmp_path, with_fields(package) + " " * (16 << 20))
    with pytest.raises(ModelPackageError, match="more than a model package sidecar's cap of 16777216"):
        load_model_package(onnx_path)


def test_a_hostile_sidecar_is_one_line_on_the_command_line(package, tmp_path, capsys) -> None:
    from lp3d.render.sample_scenes import coloured_sphere
    from lp3d.render.triplane_io import save_triplane

    onnx_path = hostile_sidecar(package, tmp_path, NESTED)
    save_triplane(tmp_path / "s.npz", coloured_sphere(size=8))
    code = main(["render", str(tmp_path / "s.npz"), "-o", str(tmp_path / "v.png"), "--model", str(onnx_path)])
    err = capsys.readouterr().err
    assert code == 1 and "m.json: unreadable model package sidecar (nested too deeply)" in err, err
    assert "Traceback" not in err and not (tmp_path / "v.png").exists()


def test_planes_the_decoder_would_overflow_are_refused_before_a_triplane_is_written(package) -> None:
    import numpy as np

    from lp3d.lift.model_package import ModelPackageError, load_model_package

    pkg = load_model_package(package["onnx"])
    assert pkg.triplane(np.ones((3, 32, 4, 4), np.float32)).planes.shape == (3, 32, 4, 4)
    with pytest.raises(ModelPackageError, match="overflows float32: on planes up to 1e\\+36"):
        pkg.triplane(np.full((3, 32, 4, 4), 1e36, np.float32))


def weights_with(package: dict, **change: object) -> dict:
    return {**package["pt"], **change}


def _int_keys(pkg: dict) -> dict:
    return weights_with(pkg, encoder={i: v for i, v in enumerate(pkg["pt"]["encoder"].values())})


def _huge_config(pkg: dict) -> dict:
    return weights_with(pkg, config={**pkg["pt"]["config"], "backbone_widths": [1 << 20] * 4})


WEIGHTS = {
    # AttributeError: 'int' object has no attribute 'startswith'.
    "int-keys": (_int_keys, "'encoder' must map parameter names to tensors; it has the key 0 (int)"),
    "int-keys-student": (
        lambda pkg: {**weights_with(pkg, encoder=None), "student": {1: torch.zeros(1)}},
        "'student' must map parameter names to tensors; it has the key 1 (int)",
    ),
    "not-a-tensor": (
        lambda pkg: weights_with(pkg, encoder={**pkg["pt"]["encoder"], "x": [1.0]}),
        "'encoder'['x'] must be a tensor, got list",
    ),
    # A configuration claiming sizes its weights do not have built (allocated) the claimed network first.
    "huge-config": (_huge_config, "encoder weights (config 'tiny') do not fit their configuration"),
    "nested-config": (lambda pkg: weights_with(pkg, config=NESTED), "config (JSON) (nested too deeply)"),
    "decoder-overflow": (
        lambda pkg: weights_with(pkg, decoder={**pkg["pt"]["decoder"], "w1": torch.full((33, 64), 1e38)}),
        "the decoder overflows float32",
    ),
    "plane-offset": (
        lambda pkg: weights_with(pkg, plane_offset=torch.zeros(2, 2)),
        "'plane_offset' must be a (3, 32, 64, 64) tensor, got (2, 2)",
    ),
}


@pytest.mark.parametrize("case", sorted(WEIGHTS))
def test_hostile_torch_weights_are_refused_at_load(package, tmp_path, case) -> None:
    from lp3d.lift.inference import load_encoder
    from lp3d.lift.model_package import ModelPackageError

    make, words = WEIGHTS[case]
    path = tmp_path / "w.pt"
    torch.save(make(package), path)
    with pytest.raises(ModelPackageError, match=re.escape(words)) as caught:
        load_encoder(path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize(
    "change, words",
    [
        ({"output_resolution": 1 << 20}, "SuperresConfig.output_resolution must be an int in [1, 4096]"),
        ({"input_resolution": 1 << 30}, "SuperresConfig.input_resolution must be an int in [1, 1024]"),
        ({"block_channels": [1 << 40]}, "SuperresConfig.block_channels must be ints in [1, 4096]"),
        ({"w_dim": True}, "SuperresConfig.w_dim must be an int"),
        ({"antialias": "yes"}, "SuperresConfig.antialias must be true or false"),
    ],
)
def test_a_torch_superres_config_is_capped_before_it_is_built(package, tmp_path, change, words) -> None:
    """A torch package's SR claiming a huge image is refused by name, not allocated."""
    from lp3d.lift.inference import load_encoder
    from lp3d.lift.model_package import ModelPackageError
    from lp3d.nets.superres import SUPERRES_CONFIGS

    config = {**SUPERRES_CONFIGS["tiny"].to_dict(), **change}
    path = tmp_path / "w.pt"
    torch.save(weights_with(package, superres={"config": config, "state": {}}), path)
    with pytest.raises(ModelPackageError, match=re.escape(words)) as caught:
        load_encoder(path, superres=True)
    assert str(path) in str(caught.value)


def test_good_torch_weights_still_load(package, tmp_path) -> None:
    import numpy as np

    from lp3d.lift.inference import load_encoder

    path = tmp_path / "w.pt"
    torch.save(package["pt"], path)
    image = np.zeros((1, 3, 128, 128), np.float32)
    assert load_encoder(path).run(image).shape == (1, 3, 32, 64, 64)
    assert load_encoder(package["onnx"]).run(image).shape == (1, 3, 32, 64, 64)


def test_every_torch_load_in_lp3d_is_weights_only() -> None:
    """Nothing is unpickled: a .pt from someone else cannot run code (promise 1)."""
    root = REPO / "python" / "lp3d"
    calls = [
        (f, line)
        for f in root.rglob("*.py")
        for line in f.read_text(encoding="utf-8").splitlines()
        if "torch.load(" in line and not line.lstrip().startswith("#")
    ]
    assert calls and all("weights_only=True" in line for _, line in calls), calls
