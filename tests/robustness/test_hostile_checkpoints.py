"""Hostile training checkpoints and checkpoint parts: ``lp3d eval`` of a checkpoint missing an entry
or holding one of the wrong type, and ``scripts/checkpoint_parts.py`` given FIFOs, devices, deep
manifests, folders for files and files for folders, end with one line naming what is wrong, never a
traceback, a hang or a MemoryError. Each test failed before."""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import torch

from lp3d.training import CheckpointError
from lp3d.training.checkpoint import load_checkpoint
from support.checkpoints import parts_module, tiny_state
from support.cli import run


@pytest.fixture(scope="module")
def parts() -> ModuleType:
    return parts_module()


@pytest.fixture(scope="module")
def state() -> dict[str, Any]:
    return tiny_state()


def _save(path: Path, state: dict[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)
    return path


EDITS: dict[str, tuple[Callable[[dict[str, Any]], None], str]] = {
    "no student": (lambda s: s.pop("student"), "'student' must be a state dict"),
    "no teacher": (lambda s: s.pop("teacher"), "'teacher' must be a string"),
    "no scene": (lambda s: s.pop("scene"), "'scene' must be a string"),
    "step as text": (lambda s: s.update(step="seven"), "'step' must be a step number"),
    "step as float": (lambda s: s.update(step=7.5), "'step' must be a step number"),
    "scene as a number": (lambda s: s.update(scene="5"), "'scene' must be the JSON of the scene bounds"),
    "student of lists": (lambda s: s.update(student={"decoder.w0": [1.0]}), "names to tensors"),
    "student without decoder": (
        lambda s: s.update(student={k: v for k, v in s["student"].items() if "decoder" not in k}),
        "has no decoder.w0",
    ),
}


@pytest.mark.parametrize("edit", sorted(EDITS))
def test_a_damaged_checkpoint_is_named_when_it_is_read(state, tmp_path, edit) -> None:
    change, words = EDITS[edit]
    damaged = {**state, "student": dict(state["student"])}
    change(damaged)
    path = _save(tmp_path / "step-000007.pt", damaged)
    with pytest.raises(CheckpointError, match=words):
        load_checkpoint(path)


@pytest.mark.parametrize("edit", ["no student", "step as text", "scene as a number", "student of lists"])
def test_lp3d_eval_says_what_is_missing_in_one_line(capsys, state, tmp_path, edit) -> None:
    damaged = {**state, "student": dict(state["student"])}
    EDITS[edit][0](damaged)
    path = _save(tmp_path / "run" / "checkpoints" / "step-000007.pt", damaged)
    code, _, err = run(capsys, "eval", path, "--baseline-steps", "0")
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "step-000007.pt" in err and EDITS[edit][1].split()[0] in err, err


def test_scene_bounds_out_of_range_are_named(state, tmp_path) -> None:
    from lp3d.training.checkpoint import student_from_checkpoint

    bad = {**state, "scene": json.dumps({"box_warp": -1.0, "ray_start": 2.25, "ray_end": 3.3})}
    ckpt = load_checkpoint(_save(tmp_path / "step-000007.pt", bad))
    with pytest.raises(CheckpointError, match="entry 'scene': box_warp"):
        student_from_checkpoint(ckpt)
    unknown = {**state, "scene": json.dumps({"box": 1.0})}
    with pytest.raises(CheckpointError, match="'scene' holds no scene bounds"):
        student_from_checkpoint(load_checkpoint(_save(tmp_path / "step-000008.pt", unknown)))


def test_every_torch_file_reader_names_a_fifo_and_a_file_that_is_not_torchs(tmp_path) -> None:
    """A FIFO given as a checkpoint was "no such file" (``lp3d eval``) or a read that waits for a
    writer; a JPEG or text file was torch's paragraph about ``weights_only``. Every reader of torch
    files goes through one (``read_torch_file``): one line each, naming the file."""
    from lp3d.export.superres import add_superres_to_weights
    from lp3d.lift.inference import load_encoder
    from lp3d.superres_fit.checkpoint import load_fit

    fifo = tmp_path / "pipe.pt"
    os.mkfifo(fifo)
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint\n")
    readers: dict[str, Callable[[Path], object]] = {
        "load_checkpoint": load_checkpoint,
        "load_fit": load_fit,
        "load_encoder": lambda p: load_encoder(p, "torch"),
        "add_superres_to_weights": lambda p: add_superres_to_weights(p, None, ""),  # type: ignore[arg-type]
    }
    for name, read in readers.items():
        err = _within(10.0, lambda read=read: read(fifo))
        assert err is not None and "pipe.pt" in str(err) and "FIFO" in str(err), (name, err)
        err = _within(10.0, lambda read=read: read(text))
        assert err is not None and "notes.pt: not a PyTorch file" in str(err), (name, err)
        assert len(str(err).splitlines()) == 1, (name, err)


def test_lp3d_eval_of_a_fifo_names_it(capsys, tmp_path) -> None:
    fifo = tmp_path / "step-000001.pt"
    os.mkfifo(fifo)
    code, _, err = run(capsys, "eval", fifo, "--baseline-steps", "0")
    assert code == 1 and "is a FIFO (named pipe), not a regular file" in err and "no such" not in err, err


# ------------------------------------------------------------------------------- checkpoint parts


@pytest.fixture(scope="module")
def manifest(parts, state, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("parts")
    ckpt = _save(folder / "run" / "step-000007.pt", state)
    return parts.split(ckpt, folder / "out", 4 << 20)


def _within(seconds: float, call: Callable[[], object]) -> BaseException | None:
    """What ``call`` raised (None if it returned), failing the test if it is still running after
    ``seconds`` (a read of a FIFO that waits for a writer)."""
    result: list[BaseException | None] = []

    def target() -> None:
        try:
            call()
            result.append(None)
        except BaseException as e:  # noqa: BLE001  (the test reports whatever it was)
            result.append(e)

    worker = threading.Thread(target=target, daemon=True)
    worker.start()
    worker.join(seconds)
    if worker.is_alive():
        pytest.fail(f"still reading after {seconds} s: a FIFO or a device was read")
    return result[0]


def test_a_fifo_manifest_or_part_is_refused_at_once(parts, manifest, tmp_path) -> None:
    fifo = tmp_path / "step-000007.parts.json"
    os.mkfifo(fifo)
    e = _within(20, lambda: parts.join(fifo, tmp_path / "x.pt"))
    assert isinstance(e, parts.PartsError) and "FIFO" in str(e), e
    listed = json.loads(manifest.read_text())
    copy = tmp_path / "m.parts.json"
    copy.write_text(json.dumps(listed))
    for i, p in enumerate(listed["parts"]):
        target = tmp_path / p["name"]
        if i == 0:
            os.mkfifo(target)
        else:
            target.write_bytes((manifest.parent / p["name"]).read_bytes())
    e = _within(20, lambda: parts.join(copy, tmp_path / "x.pt"))
    assert isinstance(e, parts.PartsError) and "FIFO" in str(e) and "part00" in str(e), e


def test_a_part_that_is_dev_zero_is_refused_not_read(parts, manifest, tmp_path) -> None:
    listed = json.loads(manifest.read_text())
    listed["parts"][0]["bytes"] = 1 << 40  # and its claim is refused too
    copy = tmp_path / "m.parts.json"
    copy.write_text(json.dumps(listed))
    with pytest.raises(parts.PartsError, match="plain file name, bytes"):
        parts.join(copy, tmp_path / "x.pt")
    listed = json.loads(manifest.read_text())
    copy.write_text(json.dumps(listed))
    (tmp_path / listed["parts"][0]["name"]).symlink_to("/dev/zero")
    e = _within(20, lambda: parts.join(copy, tmp_path / "x.pt"))
    assert isinstance(e, parts.PartsError) and "character device" in str(e), e


def test_a_deeply_nested_manifest_is_one_error(parts, tmp_path) -> None:
    deep = tmp_path / "deep.parts.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(parts.PartsError, match="nested too deeply"):
        parts.join(deep, tmp_path / "x.pt")
    huge = tmp_path / "huge.parts.json"
    huge.write_bytes(b" " * (2 << 20))
    with pytest.raises(parts.PartsError, match="more than a manifest's cap of"):
        parts.join(huge, tmp_path / "x.pt")


def test_folders_for_files_and_files_for_folders(parts, manifest, state, tmp_path, capsys) -> None:
    folder = tmp_path / "dest"
    folder.mkdir()
    with pytest.raises(parts.PartsError, match="is a folder"):
        parts.join(manifest, folder)
    afile = tmp_path / "out"
    afile.write_text("")
    ckpt = _save(tmp_path / "ckpt" / "step-000007.pt", state)
    with pytest.raises(parts.PartsError, match="is a file, not a folder"):
        parts.split(ckpt, afile, 1 << 20)
    assert parts.main(["join", str(manifest), str(afile / "x.pt")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("checkpoint_parts: error:") and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("edit", ["step as text", "no student"])
def test_split_of_a_damaged_checkpoint_is_one_line(parts, state, tmp_path, capsys, edit) -> None:
    damaged = {**state, "student": dict(state["student"])}
    EDITS[edit][0](damaged)
    ckpt = _save(tmp_path / "step-000007.pt", damaged)
    assert parts.main(["split", str(ckpt), str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "step-000007.pt" in err, err
    assert not (tmp_path / "out").exists()
