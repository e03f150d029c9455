"""Distributed training with torchrun on the CPU (gloo, 2 processes).

Two ranks at batch B/2 each follow one process at batch B (both recipes), a run whose rank is killed
resumes exactly, and a run resumed on another number of processes continues it. The runs use
``tests/support/distributed_worker.py``'s configurations (``dist-paper``: the paper's recipe with the SR, the
decoder and the discriminator all training from step 1; ``dist-cpu``: the CPU recipe) and start
``python -m torch.distributed.run --standalone`` (a free port, chosen by torchrun) as a subprocess.

Tolerance (2 ranks vs 1 process). The two compute the same sums in another order: a conv over a
batch of 2 rounds differently from one over 4, and a mean over ranks of half-batch means differs from
one mean in the last bits (the logged losses agree to 6 digits). Adam turns those last bits into
parameter differences of up to its step size wherever a gradient is near zero: its first step is
``lr·g/|g|``, and with the discriminator's beta1 = 0 every step follows the sign of the latest
gradient, so a near-zero gradient that rounds to the other sign moves an element by ``lr`` the other
way. Parameters are therefore compared by how far they moved from the common initial weights a0, per
model: ``|a - b| <= GLOBAL_RTOL·|a - a0|`` (norms over all parameters), and at most
``ELEMENT_FRACTION`` of the elements are off by more than 10 % of their own movement. Measured when
written (2 loaded cores): paper recipe, 3 steps: student 7e-4 and 0.24 %, discriminator 5e-5 to 6e-3
(a few dozen flipped elements) and under 0.01 %; CPU recipe, 4 steps: student 7e-4. The same 2-rank
paper run without the gradient average is off by 0.24 / 0.52 and 66 % / 62 % (student /
discriminator). Logged losses (the means over ranks) agree to ``LOSS_RTOL``; the data stream
(``data_rng``) is identical.

Budget: about 2 minutes on 2 loaded cores, most of it starting torch in 2 processes for each of the
four torchrun launches and the paper recipe's steps.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import torch

from lp3d.teachers import ProceduralTeacher
from lp3d.training import TrainConfig, Trainer, distributed, load_checkpoint
from lp3d.training.losses import build_perceptual
from support.distributed_worker import CONFIGS
from support.paths import TESTS

WORKER = str(TESTS / "support" / "distributed_worker.py")
GLOBAL_RTOL = 2e-2
ELEMENT_FRACTION = 2e-2
LOSS_RTOL = 1e-4
#: Paper recipe: steps of the comparison runs; the killed run is resumed from its checkpoint at 2.
PAPER_STEPS = 3
CPU_STEPS = 4
TIMEOUT_S = 300


def _env(**extra: str) -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", **extra}
    env.pop("WORLD_SIZE", None)  # torchrun sets the rest
    return env


def _torchrun_cmd(*args: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        WORKER,
        *args,
    ]


def _torchrun(*args: str) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        _torchrun_cmd(*args, "--no-progress"), env=_env(), capture_output=True, text=True, timeout=TIMEOUT_S
    )
    assert proc.returncode == 0, f"torchrun failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


def _one_process(cfg: TrainConfig, out: Path, steps: int, **kw: Any) -> Trainer:
    teacher = ProceduralTeacher(resolution=cfg.triplane_resolution)
    trainer = Trainer(
        cfg, out, teacher=teacher, perceptual=build_perceptual(cfg.perceptual), progress=False, **kw
    )
    trainer.train(steps)
    return trainer


def _initial(cfg: TrainConfig, out: Path, **kw: Any) -> dict[str, dict[str, torch.Tensor]]:
    teacher = ProceduralTeacher(resolution=cfg.triplane_resolution)
    t = Trainer(cfg, out, teacher=teacher, perceptual=build_perceptual(cfg.perceptual), progress=False, **kw)
    t.close()
    return {"student": t.student.state_dict(), "discriminator": t.discriminator.state_dict()}


def _rows(run: Path, *keys: str) -> list[tuple[str, ...]]:
    with open(run / "log.csv", newline="") as f:
        return [tuple(r[k] for k in keys) for r in csv.DictReader(f)]


def _assert_close_to(
    a: dict[str, Any], b: dict[str, Any], init: dict[str, dict[str, torch.Tensor]], parts: tuple[str, ...]
) -> None:
    """Parameters of checkpoints ``a`` and ``b`` within the stated tolerance of how far they moved."""
    for part in parts:
        num = den = 0.0
        count = off = 0
        for k, x in a[part].items():
            if not x.is_floating_point():
                continue
            diff = (x - b[part][k]).double().abs()
            moved = (x - init[part][k]).double().abs()
            num, den = num + diff.square().sum().item(), den + moved.square().sum().item()
            count, off = count + x.numel(), off + int((diff > 0.1 * moved + 1e-9).sum())
        assert den > 0, f"{part} did not train"
        assert math.sqrt(num / den) <= GLOBAL_RTOL, f"{part}: |a - b| / |a - a0| = {math.sqrt(num / den):.3g}"
        assert off <= ELEMENT_FRACTION * count, f"{part}: {off} of {count} elements differ by > 10 %"


def _assert_losses_close(run_a: Path, run_b: Path, keys: tuple[str, ...]) -> None:
    a, b = _rows(run_a, "step", *keys), _rows(run_b, "step", *keys)
    assert [r[0] for r in a] == [r[0] for r in b]
    for ra, rb in zip(a, b, strict=True):
        for key, x, y in zip(keys, ra[1:], rb[1:], strict=True):
            assert (x == "") == (y == ""), (ra[0], key)
            if x:
                assert float(x) == pytest.approx(float(y), rel=LOSS_RTOL), (ra[0], key)


# ----------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def paper(tmp_path_factory) -> dict[str, Any]:
    """``dist-paper``: 2 ranks and 1 process for PAPER_STEPS steps, and the initial weights."""
    root = tmp_path_factory.mktemp("paper")
    cfg = CONFIGS["dist-paper"]
    proc = _torchrun("--config", "dist-paper", "--max-steps", str(PAPER_STEPS), "--out", str(root / "two"))
    _one_process(cfg, root / "one", PAPER_STEPS)
    return {"root": root, "cfg": cfg, "init": _initial(cfg, root / "init"), "stderr": proc.stderr}


# ---------------------------------------------------------------------------------------- the tests
def test_two_ranks_follow_one_process_in_the_paper_recipe(paper):
    root = paper["root"]
    two, one = root / "two", root / "one"
    a = load_checkpoint(two / "checkpoints" / f"step-{PAPER_STEPS:06d}.pt")
    b = load_checkpoint(one / "checkpoints" / f"step-{PAPER_STEPS:06d}.pt")
    assert a["world_size"] == 2 and b["world_size"] == 1 and len(a["rng_other_ranks"]) == 1
    assert a["data_rng"] == b["data_rng"]  # one stream, drawn whole on every rank
    _assert_close_to(a, b, paper["init"], ("student", "discriminator"))
    keys = ("loss", "tri", "mv_col_high", "ref_col_high", "sr_col_high", "mv_adv", "d_loss", "r1")
    _assert_losses_close(two, one, keys)
    assert _rows(two, "d_loss")[1][0] != ""  # the discriminator trained
    # Rank 0 alone wrote the run directory: one row per step, the world recorded, one start line.
    assert [int(r[0]) for r in _rows(two, "step")] == list(range(PAPER_STEPS))
    assert '"world_size": 2' in (two / "world.json").read_text()
    assert paper["stderr"].count("world size 2, batch 4, 2 per rank on 2 processes (gloo)") == 1
    assert "minibatch-stddev group" not in paper["stderr"]  # groups of 2 fit 2 per rank


def test_two_ranks_follow_one_process_in_the_cpu_recipe(tmp_path):
    cfg, cache = CONFIGS["dist-cpu"], tmp_path / "cache"
    common = ["--data-cache", str(cache), "--max-steps", str(CPU_STEPS)]
    _torchrun("--config", "dist-cpu", *common, "--out", str(tmp_path / "two"))  # rank 0 builds the cache
    assert len(list(cache.iterdir())) == 2  # training and held-out datasets, nothing half-written
    _one_process(cfg, tmp_path / "one", CPU_STEPS, data_cache=cache)
    a = load_checkpoint(tmp_path / "two" / "checkpoints" / f"step-{CPU_STEPS:06d}.pt")
    b = load_checkpoint(tmp_path / "one" / "checkpoints" / f"step-{CPU_STEPS:06d}.pt")
    assert a["data_rng"] == b["data_rng"]
    _assert_close_to(a, b, _initial(cfg, tmp_path / "init", data_cache=cache), ("student",))
    _assert_losses_close(tmp_path / "two", tmp_path / "one", ("loss", "tri", "ray"))
    assert _rows(tmp_path / "two", "ray")[1][0] != ""  # the ray phase ran
    with open(tmp_path / "two" / "heldout.csv") as f:  # written once per checkpoint, by rank 0
        assert [r["step"] for r in csv.DictReader(f)] == ["0", "2", "4"]


def test_a_run_whose_rank_is_killed_resumes_exactly(paper, tmp_path):
    run, pids = tmp_path / "killed", tmp_path / "pids"
    pids.mkdir()
    args = _torchrun_cmd("--config", "dist-paper", "--max-steps", "1000", "--out", str(run), "--no-progress")
    proc = subprocess.Popen(
        args,
        env=_env(LP3D_TEST_PID_DIR=str(pids)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    first = run / "checkpoints" / "step-000002.pt"
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not first.exists():
            assert proc.poll() is None, f"the run ended early:\n{proc.communicate()[0]}"
            assert time.monotonic() < deadline, "no checkpoint in time"
            time.sleep(0.05)
        os.kill(int((pids / "rank-1.pid").read_text()), signal.SIGKILL)
        output = proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode != 0, output  # torchrun tore the run down
    rank0 = int((pids / "rank-0.pid").read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(rank0, 0)  # rank 0 went with it
    # Resume on 2 ranks from the checkpoint written before the kill (later ones may exist).
    _torchrun("--resume", str(first), "--max-steps", str(PAPER_STEPS))
    straight = load_checkpoint(paper["root"] / "two" / "checkpoints" / f"step-{PAPER_STEPS:06d}.pt")
    resumed = load_checkpoint(run / "checkpoints" / f"step-{PAPER_STEPS:06d}.pt")
    for part in ("student", "discriminator"):
        for k, v in straight[part].items():
            assert torch.equal(v, resumed[part][k]), f"{part}.{k}"
    for opt in ("optimizer_g", "optimizer_d"):
        sa, sb = straight[opt]["state"], resumed[opt]["state"]
        assert sa.keys() == sb.keys() and all(
            torch.equal(sa[i]["exp_avg_sq"], sb[i]["exp_avg_sq"]) for i in sa
        )
    assert straight["data_rng"] == resumed["data_rng"]
    for x, y in zip(
        [straight["rng"], *straight["rng_other_ranks"]],
        [resumed["rng"], *resumed["rng_other_ranks"]],
        strict=True,
    ):
        assert torch.equal(x["torch"], y["torch"])
    keys = ("step", "loss", "d_loss", "r1")
    assert _rows(run, *keys) == _rows(paper["root"] / "two", *keys)


def test_a_two_rank_run_resumes_on_one_process(paper, tmp_path, capsys):
    two = paper["root"] / "two"
    trainer = _one_process(
        paper["cfg"], tmp_path / "one", PAPER_STEPS, resume=two / "checkpoints" / "step-000002.pt"
    )
    assert "was written by a run of 2 process(es), this one has 1" in capsys.readouterr().err
    assert trainer.step == PAPER_STEPS
    a = load_checkpoint(two / "checkpoints" / f"step-{PAPER_STEPS:06d}.pt")
    b = load_checkpoint(tmp_path / "one" / "checkpoints" / f"step-{PAPER_STEPS:06d}.pt")
    assert b["world_size"] == 1 and a["data_rng"] == b["data_rng"]
    _assert_close_to(a, b, paper["init"], ("student", "discriminator"))


# ------------------------------------------------------------------------------- without processes
def test_a_batch_that_does_not_split_over_the_ranks_is_refused(monkeypatch, tmp_path):
    monkeypatch.setattr(distributed, "world_size", lambda: 2)
    cfg = dataclasses.replace(CONFIGS["dist-paper"], batch_size=3)
    with pytest.raises(ValueError, match="batch size 3 is not a multiple of the world size 2"):
        Trainer(
            cfg, tmp_path / "x", teacher=ProceduralTeacher(resolution=64), perceptual=None, progress=False
        )
    assert not (tmp_path / "x").exists()


def test_minibatch_stddev_groups_that_do_not_fit_a_rank_are_reported(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(distributed, "world_size", lambda: 2)
    cfg = CONFIGS["dist-paper"]
    cfg = dataclasses.replace(cfg, discriminator=dataclasses.replace(cfg.discriminator, mbstd_group_size=4))
    Trainer(
        cfg, tmp_path / "x", teacher=ProceduralTeacher(resolution=64), perceptual=None, progress=False
    ).close()
    assert "2 samples per rank is not a multiple of the discriminator's minibatch-stddev group (4)" in (
        capsys.readouterr().err
    )


def test_rows_are_strided_over_the_ranks_and_cover_the_batch():
    rows = list(range(8))
    shards = [distributed.shard(rows, rank_=r, size=4) for r in range(4)]
    assert shards == [[0, 4], [1, 5], [2, 6], [3, 7]]
    assert distributed.shard(rows) == rows  # one process: everything


@pytest.mark.parametrize(
    ("env", "device", "message"),
    [
        ({"WORLD_SIZE": "2", "RANK": "0"}, "auto", "LOCAL_RANK, MASTER_ADDR, MASTER_PORT not"),
        (
            {"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1", "MASTER_ADDR": "x", "MASTER_PORT": "1"},
            "cuda:1",
            "each rank uses cuda:LOCAL_RANK",
        ),
        (
            {"WORLD_SIZE": "2", "RANK": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "x", "MASTER_PORT": "1"},
            "cpu",
            "RANK=2 is outside WORLD_SIZE=2",
        ),
        ({"WORLD_SIZE": "two"}, "cpu", "WORLD_SIZE='two' is not an integer"),
    ],
)
def test_a_bad_torchrun_environment_is_a_clear_error(monkeypatch, env, device, message):
    for k in distributed.ENV_VARS:
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(distributed.DistributedSetupError, match=message):
        distributed.setup(device)
    assert distributed.world_size() == 1


def test_one_process_needs_no_process_group(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    world = distributed.setup("cpu")
    assert (world.size, world.rank, world.backend, world.device) == (1, 0, None, torch.device("cpu"))
    monkeypatch.setenv("WORLD_SIZE", "1")  # torchrun --nproc-per-node 1: the single-process path
    assert distributed.setup("cpu").size == 1
