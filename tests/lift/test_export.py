"""ONNX export of the encoder: onnxruntime agrees with PyTorch to <= 1e-3 on the triplane."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import onnx
import pytest
import torch

from lp3d.cli.export import main as export_main
from lp3d.export.package import (
    MIN_OPSET,
    check_onnx,
    export_encoder,
    reduce_plane_basis,
    round_to_float16,
    store_float16,
)
from lp3d.export.weights import training_inputs
from lp3d.lift.inference import load_encoder
from lp3d.lift.model_package import load_model_package
from lp3d.training import TRAIN_CONFIGS, Trainer, build_teacher, load_checkpoint, student_from_checkpoint
from lp3d.training.losses import build_perceptual
from lp3d.training.run_teacher import RunTeacher


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny-configuration checkpoint (untrained except for the mean-triplane start, whose zeroed last
    layer would hide encoder errors, so it and the plane generator's are given random values here;
    parity needs no training)."""
    cfg = TRAIN_CONFIGS["tiny-paper"]
    out = tmp_path_factory.mktemp("run")
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    trainer = Trainer(cfg, out, teacher=teacher, perceptual=build_perceptual("none"), progress=False)
    enc = trainer.student.encoder
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        enc.head.out_convs[-1].weight.normal_(0.0, 0.05, generator=g)
        enc.generator.to_planes.weight.normal_(0.0, 0.05, generator=g)
    return trainer.save_checkpoint()


def test_tiny_encoder_onnx_matches_torch(checkpoint, tmp_path):
    student = student_from_checkpoint(load_checkpoint(checkpoint))
    assert student.plane_offset is not None  # tiny: the exported model must include the offset
    path = export_encoder(student, tmp_path / "enc.onnx")
    model = onnx.load(str(path))
    onnx.checker.check_model(model)
    assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
    assert [i.name for i in model.graph.input] == ["image"] and [o.name for o in model.graph.output] == [
        "triplane"
    ]
    err = check_onnx(student, path, batch=3)  # batch 3 != the traced batch 1: dynamic axis
    assert err <= 1e-3
    assert check_onnx(student.encoder, export_encoder(student.encoder, tmp_path / "bare.onnx")) <= 1e-3
    print(f"\nONNX vs torch max abs error on the tiny triplane: {err:.2e}")


def test_colour_grid_encoder_onnx_matches_torch(tmp_path):
    """The colour grid (``colour_pool``) exports: its pooling of the image is traced too."""
    from lp3d.nets.encoder import build_encoder

    enc = build_encoder("tiny-colour")
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():  # both branches start at zero output: give them weights
        enc.basis.coefficients[-1].weight.normal_(0.0, 0.1, generator=g)
        enc.generator.to_planes.weight.normal_(0.0, 0.1, generator=g)
    assert check_onnx(enc, export_encoder(enc, tmp_path / "colour.onnx"), batch=2) <= 1e-4


def test_export_cli_writes_a_checked_model_and_its_package(checkpoint, tmp_path, capsys):
    out = tmp_path / "model.onnx"
    assert export_main([str(checkpoint), "-o", str(out)]) == 0
    assert out.is_file()
    msg = capsys.readouterr().out
    assert "max abs error" in msg and "<= 0.001" in msg
    package = load_model_package(out)
    ckpt = torch.load(checkpoint, weights_only=True)
    np.testing.assert_array_equal(package.w0, ckpt["student"]["decoder.w0"].numpy())
    assert package.triplane_resolution == 64 and package.image_size == TRAIN_CONFIGS["tiny-paper"].image_size
    # lp3d encode's two backends agree on the exported model and the checkpoint it came from.
    images = np.random.default_rng(0).uniform(-1, 1, (2, 3, package.image_size, package.image_size))
    images = images.astype(np.float32)
    via_onnx = load_encoder(out).run(images)
    via_torch = load_encoder(checkpoint).run(images)
    assert np.abs(via_onnx - via_torch).max() <= 1e-3


def test_export_cli_writes_float16_inference_weights(checkpoint, tmp_path, capsys):
    out, weights = tmp_path / "model.onnx", tmp_path / "model.pt"
    assert export_main([str(checkpoint), "-o", str(out), "--weights", str(weights)]) == 0
    assert "float16 inference weights" in capsys.readouterr().out
    stored = torch.load(weights, weights_only=True)
    assert stored["plane_offset"].dtype == torch.float16
    assert all(v.dtype == torch.float16 for v in stored["encoder"].values() if v.is_floating_point())
    images = np.random.default_rng(1).uniform(-1, 1, (2, 3, 128, 128)).astype(np.float32)
    via_onnx = load_encoder(out).run(images)
    via_half = load_encoder(weights).run(images)
    # float16 weights (relative rounding 2^-11 each) through ~20 layers: 9e-4 of the range measured here.
    scale = np.abs(via_onnx).max()
    err = np.abs(via_onnx - via_half).max() / scale
    print(f"\nfloat16 weights vs float32 ONNX: max abs error {err:.1e} of the triplane's range")
    assert err <= 5e-3


def test_export_errors_are_clear(checkpoint, tmp_path, capsys):
    student = student_from_checkpoint(load_checkpoint(checkpoint))
    with pytest.raises(ValueError, match=f"opset must be in \\[{MIN_OPSET}, "):
        export_encoder(student, tmp_path / "x.onnx", opset=13)
    assert export_main([str(tmp_path / "missing.pt"), "-o", str(tmp_path / "y.onnx")]) == 1
    assert "no such file" in capsys.readouterr().err


def test_plane_basis_reduction_is_exact_within_the_rank_of_its_images(checkpoint):
    student = student_from_checkpoint(load_checkpoint(checkpoint))
    basis = student.encoder.basis
    assert basis is not None and basis.components.shape[0] == 32
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():  # an untrained basis adds nothing: give it coefficients to reduce
        basis.coefficients[-1].weight.normal_(0.0, 0.05, generator=g)
    images = torch.rand(6, 3, 128, 128, generator=g) * 2 - 1
    assert reduce_plane_basis(copy.deepcopy(student), images, 32) == 0.0
    # Six images' centred basis outputs span at most 5 directions: 5 planes reproduce all six.
    reduced = copy.deepcopy(student)
    assert reduce_plane_basis(reduced, images, 5) < 1e-4
    assert reduced.encoder.basis.components.shape[0] == 5 and reduced.config.encoder.basis_components == 5
    # ...and 2 planes cannot: the change is reported, not hidden.
    assert reduce_plane_basis(copy.deepcopy(student), images, 2) > 1e-3
    with pytest.raises(ValueError, match="components must be in"):
        reduce_plane_basis(copy.deepcopy(student), images, 33)


def test_training_inputs_of_a_run_trained_elsewhere_are_its_first_identities(tmp_path):
    """--basis-components on a machine without the run's dataset synthesises only the first n
    identities, and they are the dataset's own first inputs (each a pure function of its seed)."""
    cfg = dataclasses.replace(TRAIN_CONFIGS["tiny"], dataset_identities=5)
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    full = RunTeacher.of(
        teacher, "procedural", cfg, torch.device("cpu"), data_cache=tmp_path / "a", progress=False
    )
    whole = full.open_dataset()
    assert len(whole) == 5
    images = training_inputs(cfg, "procedural", str(tmp_path / "b"), n=2)
    assert images.shape == (2, 3, cfg.image_size, cfg.image_size)
    np.testing.assert_array_equal(images.numpy(), whole.ref_image[:2].astype(np.float32))
    assert len(list((tmp_path / "b").iterdir())) == 1  # cached, the prefix alone
    # With the run's dataset cached, it is read, not synthesised again.
    again = training_inputs(cfg, "procedural", str(tmp_path / "a"), n=2)
    np.testing.assert_array_equal(again.numpy(), images.numpy())
    assert len(list((tmp_path / "a").iterdir())) == 1


def test_float16_storage_halves_the_file_and_matches_the_rounded_model(checkpoint, tmp_path):
    student = student_from_checkpoint(load_checkpoint(checkpoint))
    full = export_encoder(student, tmp_path / "f32.onnx")
    assert round_to_float16(student) > 0
    half = store_float16(export_encoder(student, tmp_path / "f16.onnx"))
    assert half.stat().st_size < 0.6 * full.stat().st_size
    assert check_onnx(student, half, batch=2) <= 1e-4  # the same float16 numbers, computed in float32
