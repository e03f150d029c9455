"""Rough edges of the EG3D path that ``scripts/eg3d_check.py`` found: a teacher whose planes
are larger than the student's (EG3D's 256² for ``tiny``'s 64²) in the CPU recipe's dataset, the
conditioning camera of ``gen_videos.py``, and ``lp3d eval --help``.

``EG3D_SRC`` (NVlabs/eg3d's ``eg3d/`` folder) additionally checks the conditioning camera against EG3D's
own ``LookAtPoseSampler``; without it that test is skipped.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from lp3d.cli.eval import main as eval_main
from lp3d.render.camera import FFHQ_FOCAL, look_at_camera
from lp3d.teachers import ProceduralTeacher
from lp3d.teachers.eg3d import CONDITIONING_CAMERAS, default_conditioning_pose
from lp3d.training import TRAIN_CONFIGS, Trainer
from lp3d.training.run_teacher import RunTeacher
from lp3d.training.synthetic_data import DatasetKey, SyntheticDataset, resize_planes, teacher_fingerprint


# ------------------------------------------------------------------- (a) larger teacher planes
class _ShapeRecordingRender:
    """A cheap stand-in for the teacher's input render that records the plane shapes it is given."""

    def __init__(self) -> None:
        self.shapes: list[tuple[int, ...]] = []

    def __call__(self, planes: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        self.shapes.append(tuple(planes.shape))
        return torch.tanh(planes[:, 0, :3, :16, :16] + cameras[:, :1, None, None])


def test_dataset_stores_a_larger_teachers_planes_at_the_students_resolution(tmp_path: Path) -> None:
    teacher = ProceduralTeacher(resolution=32)  # the student's planes are 16²
    key = DatasetKey(
        teacher="procedural",
        teacher_fingerprint=teacher_fingerprint(teacher, 0),
        first_seed=0,
        n_identities=3,
        image_size=16,
        triplane_resolution=16,
        depth_resolution=4,
        depth_resolution_importance=4,
        reference_cameras=TRAIN_CONFIGS["tiny"].reference_cameras.to_dict(),
    )
    render = _ShapeRecordingRender()
    ds = SyntheticDataset.open(key, teacher, render, root=tmp_path, progress=False, chunk=2)
    assert ds.planes.shape == (3, 3, 32, 16, 16)
    # The encoder's input is rendered from the teacher's own 32² planes ...
    assert render.shapes == [(2, 3, 32, 32, 32), (1, 3, 32, 32, 32)]
    # ... and the stored target is those planes averaged down, not a crop or a subsample.
    full = torch.from_numpy(np.stack([teacher.sample(s).planes for s in range(3)])).float()
    want = resize_planes(full, 16).numpy().astype(np.float16)
    np.testing.assert_array_equal(np.asarray(ds.planes), want)
    assert np.abs(want.astype(np.float32) - full[..., ::2, ::2].numpy()).max() > 1e-2


def test_resize_planes_keeps_the_planes_at_the_target_size_and_checks_its_input() -> None:
    planes = torch.randn(2, 3, 4, 8, 8)
    assert resize_planes(planes, 8) is planes
    # A constant plane stays constant (weights sum to one); planes and channels do not mix.
    const = torch.arange(24.0).reshape(2, 3, 4, 1, 1).expand(2, 3, 4, 8, 8)
    torch.testing.assert_close(resize_planes(const, 4), const[..., :4, :4], rtol=0, atol=1e-5)
    assert resize_planes(planes, 16).shape == (2, 3, 4, 16, 16)
    with pytest.raises(ValueError, match="planes must have shape"):
        resize_planes(planes[0], 4)
    with pytest.raises(ValueError, match="resolution must be"):
        resize_planes(planes, 0)


def test_both_recipes_regress_onto_the_same_resized_teacher_planes() -> None:
    """The CPU recipe's stored target is the paper recipe's L_tri target for the same planes."""
    cfg = TRAIN_CONFIGS["tiny"]
    planes = torch.randn(2, 3, 32, 2 * cfg.triplane_resolution, 2 * cfg.triplane_resolution)
    paper = RunTeacher.target_planes(SimpleNamespace(config=cfg), planes)  # type: ignore[arg-type]
    assert torch.equal(paper, resize_planes(planes, cfg.triplane_resolution))


def test_tiny_trains_on_a_teacher_with_larger_planes(tmp_path: Path) -> None:
    """``--config tiny --teacher eg3d`` crashed building its dataset: EG3D's planes are 256², tiny's
    64². Here a procedural teacher at twice tiny's resolution stands in for EG3D."""
    cfg = dataclasses.replace(
        TRAIN_CONFIGS["tiny"],
        batch_size=2,
        dataset_identities=2,
        heldout_identities=2,
        depth_resolution=6,
        depth_resolution_importance=4,
        checkpoint_every=1,
        sample_every=0,
    )
    teacher = ProceduralTeacher(resolution=2 * cfg.triplane_resolution)
    trainer = Trainer(
        cfg, tmp_path / "run", teacher=teacher, perceptual=None, progress=False, data_cache=tmp_path / "c"
    )
    assert trainer.dataset is not None
    t = cfg.triplane_resolution
    assert trainer.dataset.planes.shape == (2, 3, 32, t, t)
    trainer.train(1)
    assert (tmp_path / "run" / "checkpoints" / "step-000001.pt").is_file()


# ------------------------------------------------------------------- (b) gen_videos.py's camera
def test_gen_videos_conditioning_is_its_3_14_over_2_camera() -> None:
    """gen_videos.py: ``LookAtPoseSampler.sample(3.14/2, 3.14/2, pivot, radius)`` with focal 4.2647,
    i.e. yaw (3.14 - pi)/2 = -0.04563° and pitch asin(1 - 3.14/pi) = +0.02905° off frontal."""
    assert CONDITIONING_CAMERAS["gen_videos"] == (1.57, 1.57, FFHQ_FOCAL)
    pose = default_conditioning_pose()
    assert pose.shape == (25,) and pose.dtype == np.float64
    expected = look_at_camera(yaw_deg=-0.04563, pitch_deg=0.02905, focal=4.2647)
    # The angles above are rounded to 1e-5 degrees: about 5e-7 in the label's entries.
    np.testing.assert_allclose(pose, expected, rtol=0, atol=1e-6)
    # EG3D's camera centre, written out: radius (sin(phi) cos(pi - h), cos(phi), sin(phi) sin(pi - h))
    # with phi = arccos(1 - 2v/pi), h = v = 1.57.
    phi = math.acos(1.0 - 2.0 * 1.57 / math.pi)
    centre = 2.7 * np.array(
        [math.sin(phi) * math.cos(math.pi - 1.57), math.cos(phi), math.sin(phi) * math.sin(math.pi - 1.57)]
    )
    np.testing.assert_allclose(pose[[3, 7, 11]], centre, rtol=0, atol=1e-15)
    # It looks at the pivot (0, 0, 0.2): the forward axis (third column) points from the centre to it.
    forward = np.array([0.0, 0.0, 0.2]) - centre
    np.testing.assert_allclose(pose[[2, 6, 10]], forward / np.linalg.norm(forward), rtol=0, atol=1e-15)
    frontal = default_conditioning_pose(conditioning="gen_samples")
    np.testing.assert_array_equal(frontal, look_at_camera(focal=CONDITIONING_CAMERAS["gen_samples"][2]))


@pytest.mark.skipif(not os.environ.get("EG3D_SRC"), reason="EG3D_SRC (NVlabs/eg3d's eg3d/ folder) not set")
def test_conditioning_cameras_match_eg3d_scripts() -> None:
    """Both conditioning cameras against EG3D's own ``LookAtPoseSampler`` and ``FOV_to_intrinsics``,
    built as ``gen_videos.py`` and ``gen_samples.py`` build them (a subprocess: EG3D's source stays off
    this process's path)."""
    src = Path(os.environ["EG3D_SRC"]).expanduser().resolve()
    code = (
        "import json, sys, numpy as np, torch\n"
        f"sys.path.insert(0, {str(src)!r})\n"
        "from camera_utils import LookAtPoseSampler, FOV_to_intrinsics\n"
        "pivot = torch.tensor([0, 0, 0.2])\n"
        "v = LookAtPoseSampler.sample(3.14/2, 3.14/2, pivot, radius=2.7)\n"
        "kv = torch.tensor([[4.2647, 0, 0.5], [0, 4.2647, 0.5], [0, 0, 1]])\n"
        "s = LookAtPoseSampler.sample(np.pi/2, np.pi/2, pivot, radius=2.7)\n"
        "ks = FOV_to_intrinsics(18.837)\n"
        "out = {'gen_videos': torch.cat([v.reshape(16), kv.reshape(9)]).tolist(),\n"
        "       'gen_samples': torch.cat([s.reshape(16), ks.reshape(9)]).tolist()}\n"
        "print(json.dumps(out))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    eg3d = json.loads(done.stdout.strip().splitlines()[-1])
    for name in ("gen_videos", "gen_samples"):
        ours = default_conditioning_pose(conditioning=name)  # type: ignore[arg-type]
        # EG3D builds it in float32: agreement to float32 rounding.
        np.testing.assert_allclose(ours, np.asarray(eg3d[name]), rtol=0, atol=1e-6, err_msg=name)


# ------------------------------------------------------------------------- (c) eval --help
def test_eval_help_describes_the_command_in_full(capsys: pytest.CaptureFixture[str]) -> None:
    assert eval_main(["--help"]) == 0  # the entry points return their exit status (lp3d.errors)
    text = " ".join(capsys.readouterr().out.split())
    assert (
        "Evaluate a trained encoder on held-out teacher identities: does it follow its input, and how "
        "does it compare with the mean head, the teacher itself and a per-identity optimisation "
        "baseline?" in text
    )
    assert "report.json and comparison.png" in text
