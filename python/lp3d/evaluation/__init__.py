"""Evaluate a trained encoder on held-out teacher identities (``lp3d eval``): does it follow its input,
and how does it compare with the mean head, the teacher itself, ``--refine`` and a per-identity
optimisation baseline?

The modules, in the order the data flows: :mod:`~lp3d.evaluation.protocol` (what is rendered and
from where: :class:`EvalSettings`, the held-out input cameras, the truth and ceiling teachers),
:mod:`~lp3d.evaluation.metrics` (PSNR, SSIM, depth errors, the cross-identity scores),
:mod:`~lp3d.evaluation.identities` (one identity's renders, refinements and baseline, and the
report made from them), :mod:`~lp3d.evaluation.report` (report.json, the figure, the table) and
:mod:`~lp3d.evaluation.evaluate` (:func:`evaluate`, :func:`evaluate_checkpoint`). The command line is
:mod:`lp3d.cli.eval`.

May import :mod:`lp3d.training` (the student, its checkpoints and the teachers' renders) and the
layers below it; needs torch (the ``train`` extra).
"""

from lp3d.evaluation.evaluate import (
    INPUT_YAW_RANGE_DEG,
    NOVEL_VIEWS,
    EvalSettings,
    evaluate,
    evaluate_checkpoint,
    input_camera,
    input_yaws,
    reference_teachers,
    summary_table,
    write_outputs,
)

__all__ = [
    "INPUT_YAW_RANGE_DEG",
    "NOVEL_VIEWS",
    "EvalSettings",
    "evaluate",
    "evaluate_checkpoint",
    "input_camera",
    "input_yaws",
    "reference_teachers",
    "summary_table",
    "write_outputs",
]
