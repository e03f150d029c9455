"""``lp3d.superres_fit.fit`` on a tiny pair cache (resume, corrupt and stale caches) and ``lp3d export``
of its fits and of a paper-recipe checkpoint's network. The package is
``support.superres_package``'s tiny one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from lp3d.cli.export import main as export_main
from lp3d.lift.inference import load_superres
from lp3d.lift.model_package import load_model_package, superres_path
from lp3d.superres_fit.fit import FitConfig, FitError, fit_superres, load_fit
from support.superres_package import ONNX_TOLERANCE, superres_package, weights_file


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    return superres_package(tmp_path_factory)


def tiny_fit_config(**changes: object) -> FitConfig:
    base = FitConfig(
        identities=2,
        views=1,
        heldout_identities=1,
        raw_resolution=16,
        output_resolution=32,
        depth_resolution=8,
        depth_resolution_importance=8,
        input_depth_resolution=8,
        input_depth_resolution_importance=8,
        teacher_resolution=32,
        block_channels=(8,),
        w_dim=8,
        steps=4,
        batch_size=2,
        crop=8,
        checkpoint_every=2,
    )
    return FitConfig.from_dict({**base.to_dict(), **changes})


def test_superres_fit_resume_cache_and_export(package, tmp_path, capsys) -> None:
    cache, out = tmp_path / "cache", tmp_path / "fit"
    cfg = tiny_fit_config()
    result = fit_superres(package["plain"], out, cfg, cache=cache, progress=False)
    report = result.report
    assert {"superres_psnr", "bilinear_psnr", "gain_db", "superres_ssim", "direct_psnr"} <= set(report)
    assert {"teacher_superres_psnr", "teacher_bilinear_psnr", "teacher_gain_db"} <= set(report)
    assert np.asarray(Image.open(out / "heldout.png")).shape[1] > 6 * cfg.output_resolution
    assert report["pairs"] == 1 and np.isfinite(report["superres_psnr"])
    assert report["gain_db"] == pytest.approx(report["superres_psnr"] - report["bilinear_psnr"])
    assert {p.name for p in out.iterdir()} == {"superres-fit.pt", "log.csv", "report.json", "heldout.png"}
    assert len((out / "log.csv").read_text().splitlines()) == 1 + cfg.steps
    fit = load_fit(out)
    assert fit.finished and fit.step == cfg.steps and fit.config == cfg
    folders = sorted(p.name for p in cache.iterdir())
    assert len(folders) == 2 and all(f.startswith("sr-") for f in folders)

    # Running it again resumes the finished fit: nothing is rendered or trained again.
    capsys.readouterr()
    again = fit_superres(package["plain"], out, cfg, cache=cache, progress=False)
    assert "resuming" in capsys.readouterr().out and again.report == report
    # Another configuration in the same folder is refused.
    with pytest.raises(FitError, match="another configuration.*steps: 4 -> 5"):
        fit_superres(package["plain"], out, tiny_fit_config(steps=5), cache=cache, progress=False)

    # A corrupt array and a stale key are reported and rebuilt (to the same arrays: renders are
    # deterministic); the fit itself uses the rebuilt pairs.
    train = next(
        p
        for p in (cache / f for f in folders)
        if json.loads((p / "meta.json").read_text())["key"]["identities"] == 2
    )
    before = np.load(train / "target.npy")
    raw = bytearray((train / "target.npy").read_bytes())
    raw[-3] ^= 0xFF
    (train / "target.npy").write_bytes(bytes(raw))
    fit_superres(package["plain"], tmp_path / "fit2", cfg, cache=cache, progress=False)
    assert "corrupt or edited" in capsys.readouterr().err
    assert np.array_equal(np.load(train / "target.npy"), before)
    meta = json.loads((train / "meta.json").read_text())
    meta["key"]["views"] = 3
    (train / "meta.json").write_text(json.dumps(meta))
    fit_superres(package["plain"], tmp_path / "fit3", cfg, cache=cache, progress=False)
    assert "made for another key" in capsys.readouterr().err

    # Export: the fitted network joins the package (its decoder is the sphere's, like the package's).
    target = tmp_path / "pkg"
    shutil.copytree(Path(package["plain"]).parent, target)
    code = export_main(
        [
            "--superres",
            str(out / "superres-fit.pt"),
            "--package",
            str(target / "tiny.onnx"),
            "--allow-worse-superres",
        ]
    )
    printed = capsys.readouterr().out
    assert code == 0 and "onnxruntime vs PyTorch max abs error" in printed
    sr = load_superres(target / "tiny.onnx")
    assert sr is not None and (sr.input_resolution, sr.output_resolution) == (16, 32)
    pkg = load_model_package(target / "tiny.onnx")
    assert pkg.superres is not None and pkg.superres.about["heldout"]["pairs"] == 1
    assert pkg.superres.about["onnx_max_abs_error"] <= ONNX_TOLERANCE
    # ... and with --weights, into the torch backend's file too: the same network.
    weights_file(package["encoder"], target / "tiny.pt")
    code = export_main(
        [
            "--superres",
            str(out / "superres-fit.pt"),
            "--package",
            str(target / "tiny.onnx"),
            "--weights",
            str(target / "tiny.pt"),
            "--allow-worse-superres",
        ]
    )
    assert code == 0 and "updated" in capsys.readouterr().out
    sr_torch = load_superres(target / "tiny.pt")
    assert sr_torch is not None and sr_torch.backend == "torch"
    x = np.random.default_rng(2).uniform(-1, 1, (2, 32, 16, 16)).astype(np.float32)
    assert np.abs(sr_torch(x) - load_superres(target / "tiny.onnx")(x)).max() <= ONNX_TOLERANCE


def test_export_guards_on_fits(package, tmp_path, capsys) -> None:
    out = tmp_path / "fit"
    fit_superres(package["plain"], out, tiny_fit_config(), cache=tmp_path / "cache", progress=False)
    ckpt = torch.load(out / "superres-fit.pt", weights_only=True)
    target = tmp_path / "pkg"
    shutil.copytree(Path(package["plain"]).parent, target)

    def export(path: Path) -> tuple[int, str]:
        code = export_main(["--superres", str(path), "--package", str(target / "tiny.onnx")])
        return code, capsys.readouterr().err

    worse = dict(ckpt, report=json.dumps({**json.loads(ckpt["report"]), "gain_db": -0.5}))
    torch.save(worse, tmp_path / "worse.pt")
    code, err = export(tmp_path / "worse.pt")
    assert code == 1 and "does not beat bilinear upsampling" in err
    torch.save(dict(ckpt, step=2), tmp_path / "unfinished.pt")
    code, err = export(tmp_path / "unfinished.pt")
    assert code == 1 and "stopped at step 2 of 4" in err
    torch.save(
        dict(ckpt, model=json.dumps({**json.loads(ckpt["model"]), "decoder_sha256": "0" * 64})),
        tmp_path / "other.pt",
    )
    code, err = export(tmp_path / "other.pt")
    assert code == 1 and "another decoder" in err
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    code, err = export(tmp_path / "junk.pt")
    assert code == 1 and "junk.pt" in err
    assert load_model_package(target / "tiny.onnx").superres is None  # nothing was added
    assert not superres_path(target / "tiny.onnx").exists()


def test_export_of_a_paper_recipe_checkpoint_carries_its_network(tmp_path, capsys) -> None:
    """The paper recipe trains an SR with the encoder: ``lp3d export`` packages it (ONNX, sidecar
    entry, ``--weights``), and the checkpoint, the ONNX package and the weights file give the same images."""
    from lp3d.training import TRAIN_CONFIGS, Trainer, build_teacher
    from lp3d.training.losses import build_perceptual

    cfg = TRAIN_CONFIGS["tiny-paper"]
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    trainer = Trainer(
        cfg, tmp_path / "run", teacher=teacher, perceptual=build_perceptual("none"), progress=False
    )
    checkpoint = trainer.save_checkpoint()
    out, weights = tmp_path / "model.onnx", tmp_path / "model.pt"
    assert export_main([str(checkpoint), "-o", str(out), "--weights", str(weights)]) == 0
    printed = capsys.readouterr().out
    assert (
        "wrote super-resolution model.superres.onnx (features (B, 32, 64, 64) -> image (B, 3, 128, 128))"
        in printed
    )
    entry = load_model_package(out).superres
    assert entry is not None and entry.about is not None and entry.about["source"] == "training checkpoint"
    x = np.random.default_rng(3).uniform(-1, 1, (2, 32, 64, 64)).astype(np.float32)
    images = [load_superres(p)(x) for p in (out, checkpoint, weights)]  # type: ignore[misc]
    assert images[0].shape == (2, 3, 128, 128)
    assert max(float(np.abs(a - images[0]).max()) for a in images[1:]) <= ONNX_TOLERANCE
    # --no-superres leaves it out.
    assert export_main([str(checkpoint), "-o", str(tmp_path / "bare.onnx"), "--no-superres"]) == 0
    assert load_model_package(tmp_path / "bare.onnx").superres is None
    assert not superres_path(tmp_path / "bare.onnx").exists()
