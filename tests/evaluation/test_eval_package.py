"""``lp3d eval MODEL.onnx``: a model package scored on held-out identities without its training
checkpoint (the shipped model, an export). The package of a tiny run's checkpoint holds that
checkpoint's student as exported (float16 weights), and a package that cannot be evaluated is one
line naming why."""

from __future__ import annotations

import shutil

import pytest

from lp3d.cli.export import main as export_main
from lp3d.evaluation import EvalSettings, evaluate_checkpoint
from lp3d.lift.model_package import ModelPackageError
from support.cli import run

#: One identity, no baseline, one timing call: the run end to end, small.
SETTINGS = EvalSettings(n_identities=1, baseline_steps=0, baseline_mean_of=1, timing_repeats=0)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A tiny run's checkpoint and its package (``model.onnx``, ``model.json``, ``model.pt``)."""
    from lp3d.training import TRAIN_CONFIGS, Trainer, build_teacher
    from lp3d.training.losses import build_perceptual

    folder = tmp_path_factory.mktemp("package")
    cfg = TRAIN_CONFIGS["tiny"]
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    trainer = Trainer(
        cfg, folder / "run", teacher=teacher, perceptual=build_perceptual("none"), progress=False
    )
    checkpoint = trainer.save_checkpoint()
    model = folder / "model.onnx"
    assert export_main([str(checkpoint), "-o", str(model), "--weights", str(model.with_suffix(".pt"))]) == 0
    return checkpoint, model


def test_a_packages_student_is_its_checkpoints_as_exported(exported, tmp_path) -> None:
    """The package's student is the checkpoint's with its weights rounded to float16 (what ``lp3d
    export`` stores): the same planes for the same images, bit for bit, the same decoder and bounds;
    and ``lp3d eval`` runs on it end to end."""
    import torch

    from lp3d.evaluation.package_student import package_student
    from lp3d.export.weights import round_to_float16
    from lp3d.training.checkpoint import load_checkpoint, student_from_checkpoint

    checkpoint, model = exported
    reference = student_from_checkpoint(load_checkpoint(checkpoint))
    round_to_float16(reference)
    images = torch.rand(2, 3, reference.config.image_size, reference.config.image_size) * 2 - 1
    for path in (model, model.with_suffix(".pt")):
        student, about = package_student(path, torch.device("cpu"))
        with torch.no_grad():
            assert torch.equal(student.encode(images), reference.encode(images)), path
        for name in ("w0", "b0", "w1", "b1"):
            assert torch.equal(getattr(student.decoder, name), getattr(reference.decoder, name)), name
        assert student.scene == reference.scene and about["step"] is None
        assert about["train_config"].name == reference.config.name
    _, _, report = evaluate_checkpoint(model, out=tmp_path / "eval", settings=SETTINGS)
    assert report["checkpoint"] == str(model) and report["step"] is None
    assert report["student"]["novel_psnr"] > 0 and (tmp_path / "eval" / "report.json").is_file()


def test_a_package_without_its_weights_is_one_line(capsys, exported, tmp_path) -> None:
    _, model = exported
    bare = tmp_path / "bare.onnx"
    shutil.copy(model, bare)
    shutil.copy(model.with_suffix(".json"), bare.with_suffix(".json"))
    with pytest.raises(ModelPackageError, match=r"bare.pt: no such file; evaluating a package needs"):
        evaluate_checkpoint(bare, settings=SETTINGS)
    code, _, err = run(capsys, "eval", bare, "--n-identities", "1", "--baseline-steps", "0")
    assert code == 1 and len(err.strip().splitlines()) == 1 and "lp3d export --weights" in err, err
