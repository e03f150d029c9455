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
#: (how they were chosen: docs/photos-and-video.md).
DEFAULT_STEPS = RefineSettings().steps


def add_refine_argument(p: argparse.ArgumentParser, what: str = "each photo") -> None:
    p.add_argument(
        "--refine",
        type=int_in(0, MAX_STEPS),
        nargs="?",
        const=DEFAULT_STEPS,
        default=0,
        metavar="N",
        help=f"fit the lifted head to {what} for N optimisation steps (PyTorch), the last ones through "
        f"the model's super-resolution network when it has one: more likeness, same decoder. Without "
        f"N: {DEFAULT_STEPS}. Default 0: encoder only",
    )


def require_torch() -> None:
    import importlib.util

    if importlib.util.find_spec("torch") is None:
        raise CLIError(
            "--refine needs PyTorch (pip install torch); without --refine lp3d runs on onnxruntime alone"
        )
    try:
        import torch  # noqa: F401
    except ImportError as e:  # installed, but its libraries did not load (a memory limit, a broken install)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CLIError(f"--refine: PyTorch is installed but could not be loaded: {first}") from None


def refine_triplanes(
    triplanes: Sequence[Any],
    crops: Sequence[np.ndarray],
    steps: int,
    names: Sequence[str],
    poses: Sequence[tuple[float, float] | None],
    package: Any = None,
) -> list[Any]:
    """Each ``TriplaneData`` fitted to its crop (S, S, 3) uint8 for ``steps`` steps, starting from its
    pose ``(yaw, pitch)`` (found from the face's landmarks; None: searched for), through the
    super-resolution network of the model ``package`` when it has one; one progress bar over all of
    them and a line per image (the pose, input-view PSNR before and after)."""
    require_torch()
    from lp3d.lift.refine import refine, superres_module

    settings = RefineSettings(steps=steps)
    superres = superres_module(package) if package is not None else None
    total = sum(settings.total_steps(pose is not None) for pose in poses)
    bar = progress(total, "refine", unit="step")
    out = []
    try:
        for tri, crop, name, pose in zip(triplanes, crops, names, poses, strict=True):
            result = refine(tri, crop, settings, pose=pose, superres=superres, on_step=bar.update)
            sr_steps = settings.superres_steps(superres is not None)
            say(
                f"{name}: refined {steps} steps"
                + (f" (the last {sr_steps} on the super-resolved image)" if sr_steps else "")
                + f" in {result.seconds:.1f} s; camera "
                f"{'from the face' if pose is not None else 'searched for'} at yaw {result.yaw_deg:+.0f}°, "
                f"pitch {result.pitch_deg:+.0f}°; input view {result.psnr_before:.1f} -> "
                f"{result.psnr_after:.1f} dB"
            )
            out.append(result.triplane)
    finally:
        bar.close()
    return out
