"""A training run's directory survives kills, damage, a second trainer and resuming from the past
(``lp3d.training.run_dir``). Small CPU-recipe runs, a few seconds each."""

from __future__ import annotations

import csv
import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from lp3d.teachers import ProceduralTeacher
from lp3d.train import main as train_main
from lp3d.training import TRAIN_CONFIGS, CheckpointError, TrainConfig, Trainer, load_checkpoint
from lp3d.training.run_dir import RunBusyError, RunLock, checkpoints


def _cfg(**changes) -> TrainConfig:
    base = dict(batch_size=2, dataset_identities=3, heldout_identities=2, sample_every=0, checkpoint_every=1)
    return dataclasses.replace(TRAIN_CONFIGS["tiny"], **{**base, **changes})


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def _trainer(cfg: TrainConfig, out: Path, cache: Path, **kw) -> Trainer:
    teacher = ProceduralTeacher(resolution=cfg.triplane_resolution)
    return Trainer(cfg, out, teacher=teacher, perceptual=None, progress=False, data_cache=cache, **kw)


def _steps(run: Path) -> list[int]:
    return [s for s, _ in checkpoints(run)]


def _logged(run: Path) -> list[str]:
    with open(run / "log.csv", newline="") as f:
        return [r["step"] for r in csv.DictReader(f)]


def test_checkpoint_every_flag_sets_the_interval_and_may_change_on_resume(tmp_path, cache):
    run = tmp_path / "run"
    _trainer(_cfg(checkpoint_every=100), run, cache).train(1)  # only the final checkpoint
    assert _steps(run) == [1]
    common = ["--resume", str(run), "--data-cache", str(cache), "--no-progress"]
    assert train_main([*common, "--max-steps", "3", "--checkpoint-every", "1"]) == 0
    assert _steps(run) == [1, 2, 3]
    assert load_checkpoint(run)["train_config"].checkpoint_every == 1
    assert train_main([*common, "--max-steps", "4", "--checkpoint-every", "0"]) == 2  # usage


def test_a_killed_write_leaves_no_temporary_behind_for_long(tmp_path, cache, capsys):
    run = tmp_path / "run"
    _trainer(_cfg(), run, cache).train(1)
    # What atomic_path leaves when kill -9 lands between the write and the rename.
    stale = [run / "checkpoints" / ".step-000002.pt.k1ll3d.tmp.pt", run / ".log.csv.x.tmp.csv"]
    for p in stale:
        p.write_bytes(b"half a checkpoint")
    trainer = _trainer(_cfg(), run, cache, resume=run)
    assert not any(p.exists() for p in stale)
    assert "removed 2 temporary file(s)" in capsys.readouterr().err
    trainer.train(2)
    assert _steps(run) == [1, 2]


def test_an_unreadable_latest_checkpoint_falls_back_to_the_newest_good_one(tmp_path, cache, capsys):
    run = tmp_path / "run"
    _trainer(_cfg(), run, cache).train(3)
    newest = run / "checkpoints" / "step-000003.pt"
    newest.write_bytes(newest.read_bytes()[:1000])  # truncated, as by a full disk
    ckpt = load_checkpoint(run)
    assert ckpt["step"] == 2
    assert "skipped unreadable newer checkpoint(s), continuing from step-000002.pt" in capsys.readouterr().err
    trainer = _trainer(_cfg(), run, cache, resume=run)
    assert trainer.step == 2
    assert _steps(run) == [1, 2]  # the damaged one is set aside, not left to be found again
    assert (run / "checkpoints" / "superseded-at-step-000002" / "step-000003.pt").is_file()
    trainer.train(4)
    assert _steps(run) == [1, 2, 3, 4] and _logged(run) == ["0", "1", "2", "3"]
    # Asked for by name, a damaged file is an error, not a silent substitute.
    bad = run / "checkpoints" / "superseded-at-step-000002" / "step-000003.pt"
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_checkpoint(bad)
    for _, p in checkpoints(run):
        p.write_bytes(b"")
    with pytest.raises(CheckpointError, match="no checkpoint in .* is readable"):
        load_checkpoint(run)


def test_encode_eval_and_resume_take_the_same_checkpoint_of_a_run(tmp_path, cache, capsys):
    """``lp3d encode --model RUN`` (the torch backend), ``lp3d eval RUN`` and ``--resume RUN`` follow one
    rule (``lp3d.lift.run_checkpoints``): the step is parsed from the name, so step 1,000,000
    is newer than step 999,999 (a sort by name says otherwise), and a damaged newest file is skipped."""
    from lp3d.lift.inference import load_encoder

    run = tmp_path / "run"
    _trainer(_cfg(), run, cache).train(2)
    folder = run / "checkpoints"
    os.replace(folder / "step-000001.pt", folder / "step-999999.pt")
    os.replace(folder / "step-000002.pt", folder / "step-1000000.pt")
    (folder / "step-1000001.pt").write_bytes(b"half a checkpoint")
    assert sorted(p.name for p in folder.glob("step-*.pt"))[-1] == "step-999999.pt"
    assert Path(load_checkpoint(run)["path"]).name == "step-1000000.pt"
    assert load_encoder(run).description.startswith("step-1000000.pt ")
    err = capsys.readouterr().err
    assert err.count("skipped unreadable newer checkpoint(s), continuing from step-1000000.pt") == 2
    assert "step-1000001.pt" in err


def test_resuming_from_an_older_checkpoint_continues_that_branch_only(tmp_path, cache, capsys):
    run = tmp_path / "run"
    _trainer(_cfg(checkpoint_every=2), run, cache).train(6)
    assert _steps(run) == [2, 4, 6]
    older = run / "checkpoints" / "step-000002.pt"
    _trainer(_cfg(checkpoint_every=2), run, cache, resume=older).train(4)
    err = capsys.readouterr().err
    assert "continuing from step 2; 2 newer checkpoint(s)" in err
    assert _steps(run) == [2, 4]
    assert sorted(p.name for p in (run / "checkpoints" / "superseded-at-step-000002").iterdir()) == [
        "step-000004.pt",
        "step-000006.pt",
    ]
    # The next plain resume continues the new branch from step 4, and the log has each step once.
    again = _trainer(_cfg(checkpoint_every=2), run, cache, resume=run)
    assert again.step == 4
    again.train(5)
    assert _logged(run) == ["0", "1", "2", "3", "4"]
    with open(run / "heldout.csv", newline="") as f:
        assert [r["step"] for r in csv.DictReader(f)] == ["0", "2", "4", "5"]


def test_a_second_trainer_on_the_same_run_is_refused(tmp_path, cache):
    run = tmp_path / "run"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(
                f"""
                import sys
                from lp3d.training.run_dir import RunLock
                lock = RunLock({str(run)!r})
                lock.acquire()
                print("locked", flush=True)
                sys.stdin.read()
                """
            ),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        with pytest.raises(RunBusyError, match=rf"in use by another trainer \(pid {holder.pid}\)"):
            _trainer(_cfg(), run, cache)
        assert not (run / "log.csv").exists()  # refused before writing anything
    finally:
        holder.kill()  # like kill -9: the kernel drops the lock with the process
        holder.wait()
    trainer = _trainer(_cfg(), run, cache)
    with pytest.raises(RunBusyError):
        RunLock(run).acquire()  # held from construction ...
    trainer.train(1)
    with RunLock(run):  # ... until train() returns
        pass


def test_tensorboard_events_follow_the_log_and_its_resumes(tmp_path, cache):
    """``RUN/tensorboard`` holds every loss term, the learning rate, the step time, the learning curve
    and the sample sheets; a resume from an older step drops the abandoned steps' events, as
    ``log.csv`` drops their rows."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    _trainer(_cfg(checkpoint_every=2, sample_every=2), run, cache).train(4)
    older = run / "checkpoints" / "step-000002.pt"
    _trainer(_cfg(checkpoint_every=2, sample_every=2), run, cache, resume=older).train(3)
    acc = EventAccumulator(str(run / "tensorboard"), size_guidance={"images": 0, "scalars": 0}).Reload()
    tags = acc.Tags()
    expected = {"loss/total", "loss/tri", "lr", "time/seconds_per_step", "heldout/specificity_db"}
    assert expected <= set(tags["scalars"])
    # A step's losses are drawn at the number of steps done, like the checkpoint after it.
    assert [e.step for e in acc.Scalars("loss/tri")] == [int(s) + 1 for s in _logged(run)] == [1, 2, 3]
    assert [e.step for e in acc.Scalars("heldout/psnr_own")] == [0, 2, 3]
    assert tags["images"] == ["samples"] and [e.step for e in acc.Images("samples")] == [2, 3]
