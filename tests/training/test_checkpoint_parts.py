"""``scripts/checkpoint_parts.py``: a run's student weights in parts of a size limit (what a GPU
machine that hands back only small files can return) and joined back, checked; ``--resume`` refuses
such a weights-only checkpoint. ``scripts/gpu_continue.sh``, which uses it on the GPU, is checked for
the files it promises."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from types import ModuleType

import pytest
import torch

from lp3d.training import (
    CHECKPOINT_FORMAT,
    TRAIN_CONFIGS,
    CheckpointError,
    SceneBounds,
    Student,
    build_teacher,
)
from lp3d.training.checkpoint import load_checkpoint, student_from_checkpoint
from lp3d.training.resume import check_resumable
from support.paths import REPO

ROOT = REPO
SCRIPT = ROOT / "scripts" / "checkpoint_parts.py"


@pytest.fixture(scope="module")
def parts() -> ModuleType:
    spec = importlib.util.spec_from_file_location("checkpoint_parts", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A ``tiny`` run's checkpoint as the trainer writes it, optimiser state included."""
    teacher = build_teacher("procedural", triplane_resolution=64)
    cfg = TRAIN_CONFIGS["tiny"]
    torch.manual_seed(0)
    scene = SceneBounds.of(teacher.sample(0))
    student = Student(cfg, teacher.decoder(), scene)
    with torch.no_grad():
        for p in student.parameters():
            p.add_(torch.randn_like(p) * 0.01)
    path = tmp_path_factory.mktemp("run") / "checkpoints" / "step-000007.pt"
    path.parent.mkdir()
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "config": cfg.to_json(),
            "teacher": "procedural",
            "teacher_args": json.dumps({}),
            "scene": json.dumps(asdict(scene)),
            "step": 7,
            "student": student.state_dict(),
            "optimizer_g": {"state": {0: {"exp_avg": torch.ones(1000)}}},
            "world_size": 1,
        },
        path,
    )
    return path


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return student_from_checkpoint(load_checkpoint(path)).state_dict()


def test_split_then_join_gives_the_same_student_in_parts_under_the_limit(parts, checkpoint, tmp_path) -> None:
    limit = 2**20  # 1 MiB: the tiny student's ~11 MB make several parts
    manifest = parts.split(checkpoint.parent.parent, tmp_path / "out", limit)  # a run folder: its newest
    listed = json.loads(manifest.read_text())
    assert manifest.name == "step-000007.parts.json" and listed["step"] == 7 and listed["config"] == "tiny"
    files = sorted((tmp_path / "out").glob("step-000007.part[0-9]*"))
    assert [f.name for f in files] == [p["name"] for p in listed["parts"]] and len(files) > 2
    assert all(f.stat().st_size <= limit for f in files)
    joined = parts.join(manifest, tmp_path / "back" / "step-000007.pt")
    want, got = _weights(checkpoint), _weights(joined)
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)
    ckpt = load_checkpoint(joined)
    assert ckpt["weights_only"] is True and "optimizer_g" not in ckpt
    # What --resume says of it, naming what to do instead.
    with pytest.raises(CheckpointError, match="weights alone.*--init-from"):
        check_resumable(ckpt, ckpt["train_config"], "procedural")


def test_join_refuses_parts_that_differ_and_writes_nothing(parts, checkpoint, tmp_path) -> None:
    manifest = parts.split(checkpoint, tmp_path, 2**20)
    listed = json.loads(manifest.read_text())
    dest = tmp_path / "joined.pt"
    second = tmp_path / listed["parts"][1]["name"]
    good = second.read_bytes()
    second.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))  # one bit flipped
    with pytest.raises(parts.PartsError, match="part1|part01"):
        parts.join(manifest, dest)
    second.write_bytes(good[:100])  # cut short
    with pytest.raises(parts.PartsError, match="size or SHA-256"):
        parts.join(manifest, dest)
    second.unlink()
    with pytest.raises(parts.PartsError, match="cannot be read"):
        parts.join(manifest, dest)
    second.write_bytes(good)
    with pytest.raises(parts.PartsError, match="one of the parts"):
        parts.join(manifest, tmp_path / listed["parts"][0]["name"])  # never overwrite an input
    assert not dest.exists() and not list(tmp_path.glob(".*tmp*"))
    parts.join(manifest, dest)  # the parts restored: it joins
    assert dest.is_file()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m.update(format="other"), "not a manifest"),
        (lambda m: m["parts"][0].update(name="../x"), "plain file name"),
        (lambda m: m["parts"][0].update(bytes=-1), "plain file name"),
        (lambda m: m.update(parts=[]), "1 to"),
        (lambda m: m.update(bytes=m["bytes"] + 1), "do not add up"),
        (lambda m: m.update(sha256="0" * 64), "join to another file"),
    ],
)
def test_join_refuses_a_bad_manifest_naming_the_field(parts, checkpoint, tmp_path, edit, message) -> None:
    manifest = parts.split(checkpoint, tmp_path, 4 * 2**20)
    listed = json.loads(manifest.read_text())
    edit(listed)
    manifest.write_text(json.dumps(listed))
    with pytest.raises(parts.PartsError, match=message):
        parts.join(manifest, tmp_path / "joined.pt")
    assert not (tmp_path / "joined.pt").exists()


def test_the_command_line_says_what_is_wrong(checkpoint, tmp_path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, str(SCRIPT), *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=120)

    bad = run("split", str(checkpoint), str(tmp_path), "--part-mib", "0")
    assert bad.returncode == 2 and "--part-mib" in bad.stderr
    missing = run("join", str(tmp_path / "none.parts.json"), str(tmp_path / "x.pt"))
    assert missing.returncode == 1 and "cannot be read" in missing.stderr
    not_ckpt = tmp_path / "notes.pt"
    not_ckpt.write_bytes(b"not a checkpoint")
    refused = run("split", str(not_ckpt), str(tmp_path / "out"))
    assert refused.returncode == 1 and "notes.pt: not a PyTorch file" in refused.stderr
    assert not (tmp_path / "out").exists()


def test_the_gpu_script_leaves_at_most_eight_files_under_16_mib() -> None:
    # The device tool's limits (8 files, 16 MiB each, 64 MiB in all) against what the script leaves
    # for small-colour: its student's weights (float32) in parts, the manifest, its log, the archive.
    text = (ROOT / "scripts" / "gpu_continue.sh").read_text()
    part_mib = float(text.split("--part-mib ")[1].split()[0])
    assert part_mib < 16
    n_weights = sum(p.numel() for p in _small_colour_student().state_dict().values())
    weights_mib = n_weights * 4 / 2**20 + 0.1  # the torch.save container's overhead is a few KiB
    n_parts = int(-(-weights_mib // part_mib))
    assert n_parts + 3 <= 8 and weights_mib < 63  # parts, manifest, train.log, run-logs.tar.gz
    subprocess.run(["bash", "-n", str(ROOT / "scripts" / "gpu_continue.sh")], check=True)


def _small_colour_student() -> Student:
    teacher = build_teacher("procedural", triplane_resolution=64)
    return Student(TRAIN_CONFIGS["small-colour"], teacher.decoder(), SceneBounds.of(teacher.sample(0)))
