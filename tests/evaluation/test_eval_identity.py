"""``lp3d.evaluation`` tells whether the student follows its input: own vs other-identity PSNR (identity
specificity), the mean-head floor and the teacher's own-head ceiling, all against the native-resolution
(256²) procedural teacher.

Two students built directly (no training) from the ``tiny`` configuration bracket the scale:

* an *oracle* whose ``encode`` recognises the held-out input image (exactly: it is one of the inputs
  the test renders itself from the 256² teacher with :func:`lp3d.evaluation.input_camera`) and returns that
  identity's head built at the student's 64² resolution: its own PSNR must equal the ceiling's, and its
  specificity must be clearly positive;
* a *mean* student, ``Student.start_from_mean`` of the floor's mean triplane (the same head for every
  input): its own PSNR must equal the floor's and its specificity must be ~0 (exactly 0 on average up
  to float rounding, since each identity's truth appears once as "own" and n-1 times as "other").

Measured when written (2-core CPU, shared; 3 identities, 2 novel views, 4 + 4 samples per ray): the
oracle's own PSNR equals the ceiling's exactly (difference 0.0 dB: the same 64² planes, decoder and
renderer), 24.35 dB own vs 16.05 dB against the other identities, specificity +8.30 dB (SSIM 0.84);
the mean student equals the floor exactly (18.34 dB, specificity 0.0 dB); the baseline after 2 steps
18.43 dB, +0.35 dB. The whole file takes ~30 s of CPU time on one thread (~50 s wall on the shared
2-core machine).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from torch import Tensor

from lp3d.evaluation import (
    EvalSettings,
    evaluate,
    input_camera,
    input_yaws,
    reference_teachers,
    summary_table,
    write_outputs,
)
from lp3d.lift.refine import RefineSettings
from lp3d.teachers import ProceduralTeacher
from lp3d.training import TRAIN_CONFIGS, SceneBounds, Student, TrainConfig, build_teacher, render_teacher

N = 3
#: Fewer samples per ray and views than the real evaluation: the properties tested do not depend on them.
CFG: TrainConfig = dataclasses.replace(
    TRAIN_CONFIGS["tiny"], depth_resolution=4, depth_resolution_importance=4
)
SETTINGS = EvalSettings(
    n_identities=N,
    novel_views=((-30.0, 0.0), (30.0, 10.0)),
    baseline_steps=0,
    timing_repeats=0,
)
#: own PSNR vs the floor/ceiling it must reproduce exactly (same planes, same decoder, same renderer).
SAME_DB = 0.01


@pytest.fixture(scope="module")
def teacher() -> ProceduralTeacher:
    return build_teacher("procedural", triplane_resolution=CFG.triplane_resolution)  # type: ignore[return-value]


@pytest.fixture(scope="module")
def scene(teacher) -> SceneBounds:
    return SceneBounds.of(teacher.sample(CFG.eval_seed_start))


class OracleStudent(Student):
    """Encodes the held-out inputs perfectly: the input image is looked up among the known ones
    ``(image (3, S, S), planes (3, 32, T, T))`` and that identity's teacher head is returned."""

    def __init__(self, cfg: TrainConfig, decoder, scene: SceneBounds, known: list[tuple[Tensor, Tensor]]):
        super().__init__(cfg, decoder, scene)
        self.known = known

    def encode(self, image: Tensor, *, amp: bool = False) -> Tensor:
        out = []
        for im in image:
            err = [float((im.cpu() - ref).square().mean()) for ref, _ in self.known]
            k = int(np.argmin(err))
            assert err[k] < 1e-10, f"an input the oracle was not shown (nearest MSE {err[k]:.3g})"
            out.append(self.known[k][1])
        return torch.stack(out).to(image.device)


def _mean_planes(teacher: ProceduralTeacher, n: int) -> Tensor:
    lo = CFG.train_seeds[0]
    planes = np.mean([teacher.sample(lo + i).planes.astype(np.float32) for i in range(n)], axis=0)
    return torch.from_numpy(planes)


@pytest.fixture(scope="module")
def oracle_report(teacher, scene):
    truth, ceiling = reference_teachers(teacher, CFG)
    assert isinstance(truth, ProceduralTeacher) and truth.resolution == 256
    assert ceiling is teacher and teacher.resolution == CFG.triplane_resolution == 64
    dec = [torch.as_tensor(a) for a in truth.decoder()]
    known = []
    for i, yaw in enumerate(input_yaws(N)):
        seed = CFG.eval_seed_start + i
        label, _ = input_camera(CFG, seed, float(yaw))
        planes = torch.from_numpy(truth.sample(seed).planes).unsqueeze(0)
        cam = torch.from_numpy(label).float().unsqueeze(0)
        _, _, image = render_teacher(truth, planes, dec, cam, CFG, scene, raw=False)
        assert image is not None
        known.append((image[0], torch.from_numpy(ceiling.sample(seed).planes)))
    student = OracleStudent(CFG, teacher.decoder(), scene, known)
    report, _ = evaluate(student, teacher, settings=SETTINGS)
    return report


@pytest.fixture(scope="module")
def mean_report(teacher, scene):
    settings = dataclasses.replace(
        SETTINGS, baseline_steps=2, refine=RefineSettings(steps=6, pose_steps=4), flip_average=True
    )
    torch.manual_seed(0)
    student = Student(CFG, teacher.decoder(), scene)
    student.start_from_mean(_mean_planes(teacher, settings.baseline_mean_of))
    return evaluate(student, teacher, settings=settings)


def test_oracle_student_reaches_the_ceiling_and_is_identity_specific(oracle_report):
    s, floor, ceiling = oracle_report["student"], oracle_report["floor"], oracle_report["ceiling"]
    print("\n" + summary_table(oracle_report))
    print(f"oracle own - ceiling: {s['novel_psnr'] - ceiling['novel_psnr']:.2e} dB")
    assert abs(s["novel_psnr"] - ceiling["novel_psnr"]) < SAME_DB
    assert abs(s["novel_ssim"] - ceiling["novel_ssim"]) < 1e-3
    assert abs(s["novel_psnr_other"] - ceiling["novel_psnr_other"]) < SAME_DB
    for row in oracle_report["per_identity"]:
        assert abs(row["novel_psnr"] - row["ceiling_novel_psnr"]) < SAME_DB
        assert row["identity_specificity_db"] > 1.0, row
    assert oracle_report["identity_specificity_db"] == s["identity_specificity_db"] > 3.0
    assert s["identity_specificity_ssim"] > 0.1
    # The 64² head is close to, not equal to, the 256² truth; the mean head is far below it.
    assert floor["novel_psnr"] + 3.0 < ceiling["novel_psnr"] < 60.0
    assert s["input_psnr"] > floor["novel_psnr"]


def test_mean_student_sits_on_the_floor_with_no_identity_specificity(mean_report):
    report, _ = mean_report
    s, floor = report["student"], report["floor"]
    print("\n" + summary_table(report))
    print(
        f"mean student own - floor: {s['novel_psnr'] - floor['novel_psnr']:.2e} dB, "
        f"specificity {report['identity_specificity_db']:.2e} dB"
    )
    assert abs(s["novel_psnr"] - floor["novel_psnr"]) < SAME_DB
    assert abs(s["novel_ssim"] - floor["novel_ssim"]) < 1e-3
    assert abs(report["identity_specificity_db"]) < 0.5
    assert abs(s["identity_specificity_ssim"]) < 0.01
    assert abs(floor["identity_specificity_db"]) < 1e-6  # one head for all: 0 by construction
    for row in report["per_identity"]:
        assert abs(row["novel_psnr"] - row["floor_novel_psnr"]) < SAME_DB
    assert floor["novel_psnr"] < report["ceiling"]["novel_psnr"]


def test_flip_averaged_mean_student_is_one_symmetric_head(mean_report):
    """Flip-averaging a student that ignores its input gives one head for every input, the mean
    head made mirror-symmetric: still no identity specificity, but a different head from the
    student's (the mean of 16 training heads is not symmetric), so the flipped pass really ran."""
    report, _ = mean_report
    s, f = report["student"], report["flip_averaged"]
    assert abs(f["identity_specificity_db"]) < 0.5
    assert abs(f["novel_psnr"] - s["novel_psnr"]) > 1e-3
    assert f["encode_ms"] > 0
    for row in report["per_identity"]:
        for key in ("flip_averaged_input_psnr", "flip_averaged_novel_psnr"):
            assert np.isfinite(row[key]), key
    assert "\nflip_averaged" in summary_table(report)


def test_report_holds_per_identity_rows_and_every_section(mean_report, tmp_path):
    report, rows = mean_report
    report_path, png = write_outputs(report, rows, tmp_path)
    data = json.loads(report_path.read_text())
    assert data["identity_seeds"] == [CFG.eval_seed_start + i for i in range(N)]
    assert data["truth"]["plane_resolution"] == 256 and data["triplane_resolution"] == 64
    per = data["per_identity"]
    assert len(per) == N and [r["seed"] for r in per] == data["identity_seeds"]
    yaws = [r["input_yaw_deg"] for r in per]
    assert sorted(yaws) == [-35.0, 0.0, 35.0] and yaws == data["input_yaw_deg"]
    for r in per:
        for key in (
            "input_pitch_deg",
            "novel_psnr",
            "novel_psnr_other",
            "identity_specificity_db",
            "novel_ssim",
            "novel_ssim_other",
            "floor_novel_psnr",
            "ceiling_novel_psnr",
            "baseline_novel_psnr",
        ):
            assert np.isfinite(r[key]), key
    for method in ("student", "baseline"):
        for key in ("input_psnr", "input_ssim", "novel_depth_l1", "novel_depth_rmse"):
            assert np.isfinite(data[method][key]), (method, key)
    for method in ("student", "baseline", "floor", "ceiling"):
        for key in (
            "novel_psnr",
            "novel_ssim",
            "novel_psnr_other",
            "novel_ssim_other",
            "identity_specificity_db",
        ):
            assert np.isfinite(data[method][key]), (method, key)
    assert data["student"]["encode_ms"] > 0 and data["baseline"]["fit_s"] > 0
    # --refine: scored per identity beside the student, at the true camera (as the baseline) and at
    # the camera found from the image (as a photo's).
    for r in per:
        for key in (
            "input_psnr",
            "refined_input_psnr",
            "refined_novel_psnr",
            "refined_identity_specificity_db",
            "photo_refined_input_psnr",
            "photo_refined_novel_psnr",
        ):
            assert np.isfinite(r[key]), key
        assert len(r["found_camera_yaw_pitch_deg"]) == 2
        assert r["true_camera_yaw_pitch_deg"] == pytest.approx([r["input_yaw_deg"], r["input_pitch_deg"]])
    assert data["refined"]["settings"]["steps"] == 6 and data["refined"]["refine_s"] > 0
    photo = data["refined_photo"]
    assert photo["refine_s"] > 0 and 0 <= photo["camera_yaw_error_deg"] < 90
    # Six steps from the mean head already move the input view towards its photo.
    assert data["refined"]["input_psnr"] > data["student"]["input_psnr"]
    assert np.isfinite(data["identity_specificity_db"])
    # The figure: per identity teacher, student, refined, baseline, ceiling rows of (input + 2 views).
    from PIL import Image

    im = Image.open(png)
    s = CFG.image_size
    assert im.height >= N * 5 * s and im.width >= 3 * s
    table = summary_table(data)
    for method in ("student", "refined", "refined_photo", "baseline", "floor", "ceiling"):
        assert f"\n{method}" in table


def test_input_yaws_cover_the_range_in_a_spread_order():
    assert input_yaws(1).tolist() == [0.0]
    y = input_yaws(16)
    assert np.allclose(np.sort(y), np.linspace(-35, 35, 16))
    first = y[:8]  # what the figure shows
    assert first.min() < -20 and first.max() > 20
    assert input_yaws(2).tolist() == [-35.0, 35.0]
