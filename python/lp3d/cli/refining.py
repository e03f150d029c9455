"""``--refine N`` of ``lp3d encode``, ``lp3d demo`` and ``lp3d video``: the encoder's triplane fitted
to its own photo for N steps (:mod:`lp3d.lift.refine`), with a progress bar and a line per image."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

import numpy as np

from lp3d.cli.common import CLIError, int_in, progress, say
from lp3d.lift.refine_settings import MAX_STEPS, RefineSettings

#: The steps a user who asks for refinement without a number gets: ``RefineSettings``' default
#: (``bench/RESULTS.md``, "Refinement": within 5 s per image on a 2-core CPU).
DEFAULT_STEPS = RefineSettings().steps


def add_refine_argument(p: argparse.ArgumentParser, what: str = "each photo") -> None:
    p.add_argument(
        "--refine",
        type=int_in(0, MAX_STEPS),
        nargs="?",
        const=DEFAULT_STEPS,
        default=0,
        metavar="N",
        help=f"fit the lifted head to {what} for N optimisation steps (PyTorch; about 0.1 s a step on a "
        f"CPU): sharper likeness, same decoder. Without N: {DEFAULT_STEPS}. Default 0: encoder only",
    )


def require_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise CLIError(
            "--refine needs PyTorch (pip install torch); without --refine lp3d runs on onnxruntime alone"
        ) from None


def refine_triplanes(
    triplanes: Sequence[Any],
    crops: Sequence[np.ndarray],
    steps: int,
    names: Sequence[str],
    poses: Sequence[tuple[float, float] | None],
) -> list[Any]:
    """Each ``TriplaneData`` fitted to its crop (S, S, 3) uint8 for ``steps`` steps, starting from its
    pose ``(yaw, pitch)`` (found from the face's landmarks; None: searched for); one progress bar over
    all of them and a line per image (the pose, input-view PSNR before and after)."""
    require_torch()
    from lp3d.lift.refine import refine

    settings = RefineSettings(steps=steps)
    total = sum(settings.total_steps(pose is not None) for pose in poses)
    bar = progress(total, "refine", unit="step")
    out = []
    try:
        for tri, crop, name, pose in zip(triplanes, crops, names, poses, strict=True):
            result = refine(tri, crop, settings, pose=pose, on_step=bar.update)
            say(
                f"{name}: refined {steps} steps in {result.seconds:.1f} s; camera "
                f"{'from the face' if pose is not None else 'searched for'} at yaw {result.yaw_deg:+.0f}°, "
                f"pitch {result.pitch_deg:+.0f}°; input view {result.psnr_before:.1f} -> "
                f"{result.psnr_after:.1f} dB"
            )
            out.append(result.triplane)
    finally:
        bar.close()
    return out
