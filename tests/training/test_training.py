"""Training on the CPU with the paper's two-stage recipe (``tiny-paper``): it learns, resumes exactly,
and fails clearly. The CPU recipe (``tiny``/``small``) is tested in ``tests/training/test_cpu_recipe.py``.

Budget: the whole file runs in under 5 minutes on 2 cores. The learning test trains the ``tiny``
configuration for ``LEARN_STEPS`` steps of batch 2 (stage 1, the procedural teacher, the weight-free
``ssim-grad`` perceptual loss) and asks for a rise of at least ``MIN_GAIN_DB`` in held-out novel-view
PSNR (the final, super-resolved 128² images) over the same model untrained. Measured when this test
was written (2-core CPU, 40 steps, 3 held-out identities x 4 views): 8.98 -> 16.66 dB (+7.7 dB),
most of it the SR learning from scratch; the raw 64² renders start at the mean teacher triplane's
17.4 dB (``mean_triplane_offset``) and stay within 0.5 dB of it in so few steps; SSIM -0.08 -> 0.10.
With 30 steps the margin is smaller but still several dB.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lp3d.cli.eval import main as eval_main
from lp3d.evaluation import EvalSettings, evaluate
from lp3d.teachers import ProceduralTeacher
from lp3d.train import main as train_main
from lp3d.training import (
    TRAIN_CONFIGS,
    CheckpointError,
    NonFiniteError,
    TrainConfig,
    Trainer,
    build_teacher,
    load_checkpoint,
    student_from_checkpoint,
)
from lp3d.training.losses import build_perceptual
from lp3d.training.run_dir import latest_checkpoint

LEARN_STEPS = 30
MIN_GAIN_DB = 2.0
EVAL = EvalSettings(n_identities=2, baseline_steps=0, timing_repeats=1)


def _tiny(**changes) -> TrainConfig:
    return dataclasses.replace(TRAIN_CONFIGS["tiny-paper"], **changes)


def _trainer(cfg: TrainConfig, out: Path, **kw) -> Trainer:
    teacher = build_teacher("procedural", triplane_resolution=cfg.triplane_resolution)
    return Trainer(
        cfg, out, teacher=teacher, perceptual=build_perceptual(cfg.perceptual), progress=False, **kw
    )


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """The tiny configuration before and after LEARN_STEPS steps, evaluated on held-out identities."""
    out = tmp_path_factory.mktemp("learn")
    cfg = _tiny(batch_size=2, checkpoint_every=LEARN_STEPS, sample_every=LEARN_STEPS)
    trainer = _trainer(cfg, out)
    before, _ = evaluate(trainer.student, trainer.teacher, settings=EVAL)
    trainer.train(LEARN_STEPS)
    after, _ = evaluate(trainer.student, trainer.teacher, settings=EVAL)
    return {"out": out, "trainer": trainer, "before": before, "after": after}


def test_tiny_training_raises_held_out_novel_view_psnr(learned):
    before, after = learned["before"]["student"], learned["after"]["student"]
    gain = after["novel_psnr"] - before["novel_psnr"]
    print(
        f"\nnovel-view PSNR {before['novel_psnr']:.2f} -> {after['novel_psnr']:.2f} dB (+{gain:.2f}); "
        f"raw {before['novel_psnr_raw']:.2f} -> {after['novel_psnr_raw']:.2f} dB; "
        f"input view {before['input_psnr']:.2f} -> {after['input_psnr']:.2f} dB"
    )
    assert gain >= MIN_GAIN_DB
    assert after["novel_ssim"] > before["novel_ssim"]
    # The triplane starts at the teacher mean; a few noisy batch-2 steps must not wreck it.
    assert after["novel_psnr_raw"] > before["novel_psnr_raw"] - 1.5


def test_run_directory_holds_config_log_checkpoint_and_samples(learned):
    out = learned["out"]
    cfg = TrainConfig.from_json((out / "config.json").read_text())
    assert cfg == learned["trainer"].config and cfg.name == "tiny-paper"
    with open(out / "log.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == list(range(LEARN_STEPS))
    assert all(np.isfinite(float(r["loss"])) for r in rows)
    assert rows[0]["reference"] == "1" and rows[1]["reference"] == "0"  # every 10th step in stage 1
    assert rows[10]["reference"] == "1" and rows[0]["ref_col_high"] != "" and rows[1]["ref_col_high"] == ""
    assert all(r["sr_col_high"] != "" and r["d_loss"] == "" for r in rows)  # stage 1: SR from teacher pairs
    ckpt = latest_checkpoint(out)
    assert ckpt is not None and ckpt.name == f"step-{LEARN_STEPS:06d}.pt"
    assert (out / "samples" / f"step-{LEARN_STEPS:06d}.png").is_file()
    # A plain state dict: loads with weights_only=True and rebuilds the student exactly.
    raw = torch.load(ckpt, weights_only=True)
    assert raw["step"] == LEARN_STEPS and isinstance(raw["config"], str)
    student = student_from_checkpoint(load_checkpoint(ckpt))
    for k, v in learned["trainer"].student.state_dict().items():
        assert torch.equal(student.state_dict()[k], v.cpu()), k


def test_eval_cli_writes_report_and_comparison_png(learned, tmp_path):
    ckpt = latest_checkpoint(learned["out"])
    out = tmp_path / "eval"
    rc = eval_main([str(ckpt), "--n-identities", "1", "--baseline-steps", "2", "--out", str(out)])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert report["step"] == LEARN_STEPS and report["identity_seeds"] == [1_000_000]
    for method in ("student", "baseline"):
        for key in (
            "input_psnr",
            "novel_psnr",
            "input_ssim",
            "novel_ssim",
            "novel_depth_l1",
            "novel_depth_rmse",
        ):
            assert np.isfinite(report[method][key]), (method, key)
    assert report["student"]["encode_ms"] > 0 and report["baseline"]["fit_s"] > 0
    assert report["lpips"] is None or report["student"]["novel_lpips"] >= 0
    from PIL import Image

    png = Image.open(out / "comparison.png")
    s = TRAIN_CONFIGS["tiny-paper"].image_size
    assert png.height >= 3 * s and png.width >= 5 * s  # teacher/student/baseline x (input + 4 views)


def test_exact_resume_matches_an_uninterrupted_run_bit_for_bit(tmp_path):
    # 4 steps straight vs 2 + resume + 2. Stage 2 from step 1, so the resumed half continues the
    # discriminator's optimiser (R1 every step) and the reference schedule; fewer samples per ray keep
    # it quick (the property does not depend on them).
    cfg = _tiny(
        batch_size=1,
        warmup_steps=1,
        dense_reference_from=3,
        r1_interval=1,
        depth_resolution=8,
        depth_resolution_importance=4,
        checkpoint_every=2,
        sample_every=0,
    )
    straight = _trainer(cfg, tmp_path / "straight")
    straight.train(4)
    first = _trainer(cfg, tmp_path / "resumed")
    first.train(2)
    second = _trainer(cfg, tmp_path / "resumed", resume=tmp_path / "resumed")
    assert second.step == 2
    second.train(4)
    a, b = straight.state_dict(), second.state_dict()
    for part in ("student", "discriminator"):
        for k, v in a[part].items():
            assert torch.equal(v, b[part][k]), f"{part}.{k}"
    assert a["data_rng"] == b["data_rng"] and torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    sa, sb = a["optimizer_g"]["state"], b["optimizer_g"]["state"]
    assert sa.keys() == sb.keys() and all(torch.equal(sa[i]["exp_avg"], sb[i]["exp_avg"]) for i in sa)
    da, db = a["optimizer_d"]["state"], b["optimizer_d"]["state"]
    assert da and all(torch.equal(da[i]["exp_avg_sq"], db[i]["exp_avg_sq"]) for i in da)

    def losses(run: str) -> list[tuple[str, str, str]]:
        with open(tmp_path / run / "log.csv") as f:
            return [(r["step"], r["loss"], r["d_loss"]) for r in csv.DictReader(f)]

    assert losses("straight") == losses("resumed")
    assert losses("straight")[3][2] != ""  # stage 2 trained the discriminator


def test_checkpoint_from_another_config_is_a_clear_error(learned, tmp_path, capsys):
    ckpt = latest_checkpoint(learned["out"])
    with pytest.raises(CheckpointError, match=r"configuration 'tiny-paper'.*requested 'small-paper'"):
        _trainer(TRAIN_CONFIGS["small-paper"], tmp_path / "small", resume=ckpt)
    with pytest.raises(CheckpointError, match="batch_size: 2 != 3"):
        _trainer(_tiny(batch_size=3), tmp_path / "b3", resume=ckpt)
    assert train_main(["--config", "small-paper", "--resume", str(ckpt), "--out", str(tmp_path / "x")]) == 1
    assert "trained with configuration 'tiny-paper', not 'small-paper'" in capsys.readouterr().err
    # An existing run is never overwritten by a fresh start.
    with pytest.raises(CheckpointError, match="already holds checkpoints"):
        _trainer(learned["trainer"].config, learned["out"])
    bad = tmp_path / "bad.pt"
    torch.save({"format": "something else"}, bad)
    with pytest.raises(CheckpointError, match="not an lp3d training checkpoint"):
        load_checkpoint(bad)


class _BrokenTeacher(ProceduralTeacher):
    """A teacher with its own super-resolution (``superresolve``, as EG3D's) that returns bad images."""

    def __init__(self, resolution: int, mode: str) -> None:
        super().__init__(resolution)
        self.mode = mode

    def superresolve(self, features: torch.Tensor) -> torch.Tensor:
        img = torch.zeros(features.shape[0], 3 if self.mode == "nan" else 4, 256, 256)
        if self.mode == "nan":
            img[-1, 0, 5, 5] = float("nan")
        return img  # 256 is resized to the image size (128): the EG3D SR's 512 also is


def test_nan_batches_and_wrong_sizes_are_clear_errors(tmp_path):
    cfg = _tiny(batch_size=2)
    nan = Trainer(cfg, tmp_path / "nan", teacher=_BrokenTeacher(64, "nan"), perceptual=None, progress=False)
    with pytest.raises(
        NonFiniteError, match=r"step 0: NaN/Inf in the teacher's reference image .* seed\(s\) \[\d+\]"
    ):
        nan.synthesize(0)
    small = Trainer(
        cfg, tmp_path / "size", teacher=_BrokenTeacher(64, "rgba"), perceptual=None, progress=False
    )
    with pytest.raises(ValueError, match=r"reference image \(encoder input\) has shape \(2, 4, 128, 128\)"):
        small.synthesize(0)
    with pytest.raises(ValueError, match="image size must be 128x128"):
        small.student.encode(torch.zeros(1, 3, 64, 64))
    with pytest.raises(ValueError, match="3 channels"):
        small.student.encode(torch.zeros(1, 4, 128, 128))

    class NaNLoss(torch.nn.Module):
        def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            return (a - b).mean() * float("nan")

    bad_loss = _trainer(_tiny(batch_size=1), tmp_path / "loss")
    bad_loss.losses.perceptual = NaNLoss()
    with pytest.raises(NonFiniteError, match="step 0: the training loss is nan"):
        bad_loss.train_step()


def test_train_is_a_plain_function_that_raises(tmp_path):
    """``lp3d.training.train()`` is the library call behind ``lp3d train``: it returns where the run
    stopped and raises (not prints) what is wrong."""
    from lp3d.training import CheckpointError, TrainResult, train

    result = train("tiny-paper", out=tmp_path / "lib", max_steps=1, batch=1, progress=False)
    assert isinstance(result, TrainResult) and result.step == 1 and not result.interrupted
    assert result.checkpoint == tmp_path / "lib" / "checkpoints" / "step-000001.pt"
    assert result.checkpoint.is_file()
    with pytest.raises(ValueError, match="'no-such': not one of .*tiny"):
        train("no-such", out=tmp_path / "x")
    with pytest.raises(ValueError, match="--batch must be >= 1"):
        train("tiny-paper", out=tmp_path / "x", batch=0)
    with pytest.raises(CheckpointError, match="configuration 'tiny-paper', not 'small'"):
        train("small", resume=result.checkpoint)
    assert not (tmp_path / "x").exists()


def test_train_cli_runs_and_reports_bad_inputs(tmp_path, capsys):
    out = tmp_path / "cli"
    assert train_main(["--config", "tiny-paper", "--max-steps", "1", "--batch", "1", "--out", str(out)]) == 0
    assert (out / "checkpoints" / "step-000001.pt").is_file() and (out / "config.json").is_file()
    err = capsys.readouterr().err
    assert "train tiny-paper" in err and "step" in err  # the progress bar
    # Resuming past the end does nothing; resuming an existing run directory picks its latest checkpoint.
    assert train_main(["--resume", str(out), "--max-steps", "1"]) == 0
    assert "nothing to do" in capsys.readouterr().err
    assert train_main(["--config", "tiny-paper", "--teacher", "eg3d", "--out", str(tmp_path / "e")]) == 1
    assert "EG3D" in capsys.readouterr().err
    assert (
        train_main(
            [
                "--config",
                "tiny-paper",
                "--perceptual",
                "lpips",
                "--lpips-weights",
                str(tmp_path / "none.pth"),
                "--out",
                str(tmp_path / "l"),
            ]
        )
        == 1
    )
    assert "--lpips-weights" in capsys.readouterr().err
