"""``--init-from`` (lp3d.training.warm_start): a new run's encoder starts from trained weights, and
a configuration that grows the network (a colour grid, more basis components) starts exactly where
the old one ended."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from lp3d.nets.encoder_config import CONFIGS as ENCODER_CONFIGS
from lp3d.training import TRAIN_CONFIGS, SceneBounds, Student, build_teacher
from lp3d.training.warm_start import WarmStartError, warm_start


@pytest.fixture(scope="module")
def teacher():
    return build_teacher("procedural", triplane_resolution=64)


def _student(teacher, name: str, *, basis: int | None = None, seed: int = 0) -> Student:
    cfg = TRAIN_CONFIGS[name]
    if basis is not None:
        cfg = dataclasses.replace(cfg, encoder=dataclasses.replace(cfg.encoder, basis_components=basis))
    torch.manual_seed(seed)
    student = Student(cfg, teacher.decoder(), SceneBounds.of(teacher.sample(0))).eval()
    g = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():  # a "trained" source: every branch adds something
        for p in student.encoder.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.01)
        student.plane_offset.normal_(0.0, 0.1, generator=g)
    return student


def _package(student: Student, path) -> None:
    """The layout of a shipped model package's weights (lp3d/lift/models/small.pt)."""
    enc = student.encoder
    torch.save(
        {
            "config": enc.config.to_dict(),
            "encoder": enc.state_dict(),
            "plane_offset": student.plane_offset.detach(),
        },
        path,
    )


class _Sneaky:
    """An object whose unpickling would run code (it records that it did)."""

    ran = False

    def __reduce__(self):
        return (_Sneaky._run, ())

    @staticmethod
    def _run() -> None:
        _Sneaky.ran = True


def _image(seed: int = 5) -> torch.Tensor:
    return torch.rand(2, 3, 128, 128, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def test_a_grown_network_starts_where_the_old_one_ended(teacher, tmp_path) -> None:
    # The source: tiny with 16 basis components; the run: tiny-colour (a colour grid, 32 components).
    old = _student(teacher, "tiny", basis=16)
    _package(old, tmp_path / "old.pt")
    new = _student(teacher, "tiny-colour", seed=7)
    before = new.encode(_image()).detach()
    started = warm_start(new, tmp_path / "old.pt")
    assert set(started.grown) == {
        "basis.components",
        "basis.coefficients.1.weight",  # the colour grid's inputs
        "basis.coefficients.3.weight",  # the 16 new components' rows
        "basis.coefficients.3.bias",
        "generator.code.1.weight",
    }
    assert started.copied == len(new.encoder.state_dict())
    with torch.no_grad():
        want, got = old.encode(_image()), new.encode(_image())
    assert not torch.allclose(before, got)  # it did change the new network ...
    assert torch.allclose(got, want, atol=1e-5, rtol=0)  # ... into the old one's function
    # ... and the new parts can learn: the colour grid's inputs get gradients.
    new.encode(_image()).square().mean().backward()
    grid = new.encoder.generator.code[1].weight.grad[:, ENCODER_CONFIGS["tiny"].code_inputs :]
    assert grid.abs().sum() > 0
    record = json.loads(started.to_json())
    assert record["source"].endswith("old.pt") and len(record["sha256"]) == 64


def test_a_run_checkpoint_is_a_source_too(teacher, tmp_path) -> None:
    old = _student(teacher, "tiny")
    torch.save(
        {"config": old.config.to_json(), "student": old.state_dict(), "step": 3}, tmp_path / "step-000003.pt"
    )
    new = _student(teacher, "tiny", seed=9)
    warm_start(new, tmp_path / "step-000003.pt")
    with torch.no_grad():
        assert torch.equal(new.encode(_image()), old.encode(_image()))


def test_sources_that_do_not_fit_are_refused_naming_why(teacher, tmp_path) -> None:
    new = _student(teacher, "tiny")
    before = {k: v.clone() for k, v in new.encoder.state_dict().items()}
    _package(_student(teacher, "tiny-colour"), tmp_path / "bigger.pt")  # larger than the run: no
    cases = {
        tmp_path / "missing.pt": "no such checkpoint file",
        tmp_path / "bigger.pt": r"basis.coefficients.1.weight has shape \(256, 1216\).*may grow",
        tmp_path / "list.pt": "a checkpoint must hold a dict",
        tmp_path / "other.pt": "checkpoint layout not understood",
        tmp_path / "text.pt": r"text.pt: not a PyTorch file \(torch.save's zip format",
    }
    torch.save([1, 2], tmp_path / "list.pt")
    torch.save({"weights": {}}, tmp_path / "other.pt")
    (tmp_path / "text.pt").write_text("not torch")
    small = dataclasses.replace(ENCODER_CONFIGS["tiny"], backbone_widths=(8, 16, 32, 64))
    from lp3d.nets.encoder import build_encoder

    torch.save(
        {"config": small.to_dict(), "encoder": build_encoder(small).state_dict()}, tmp_path / "narrow.pt"
    )
    cases[tmp_path / "narrow.pt"] = r"backbone.stem.weight has shape \(8, 5, 7, 7\)"
    torch.save({"encoder": _Sneaky()}, tmp_path / "code.pt")  # unpickling would run code: refused
    cases[tmp_path / "code.pt"] = "code.pt: cannot be read as a checkpoint or weights file: Weights only load"
    for path, match in cases.items():
        with pytest.raises(WarmStartError, match=match):
            warm_start(new, path)
    assert not _Sneaky.ran
    after = new.encoder.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # nothing half-copied


def test_init_from_is_for_new_runs_only(tmp_path) -> None:
    from lp3d.training import train

    with pytest.raises(ValueError, match="--init-from starts a new run"):
        train("tiny", out=tmp_path / "run", resume=tmp_path / "old", init_from=tmp_path / "w.pt")
