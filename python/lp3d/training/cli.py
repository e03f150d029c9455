"""The command line of training (``python -m lp3d.train`` and ``lp3d train``): its options
(:func:`add_arguments`) and :func:`main`, which builds the teacher and the :class:`Trainer` and runs it.

The last module of :mod:`lp3d.training`; nothing in the package imports it."""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

from lp3d.errors import EXIT_ERROR, EXIT_INTERRUPTED, int_in, renderer_setup_error, run_command
from lp3d.training import distributed
from lp3d.training.checkpoint import CheckpointError, load_shared_checkpoint
from lp3d.training.config import TRAIN_CONFIGS, TrainConfig, scaled_schedule
from lp3d.training.losses import PERCEPTUAL_KINDS, build_perceptual
from lp3d.training.resume import extended_schedule
from lp3d.training.run_dir import latest_checkpoint
from lp3d.training.steps import NonFiniteError
from lp3d.training.teacher_factory import (
    TEACHERS,
    build_teacher,
    recordable_teacher_args,
    resolve_teacher_args,
)
from lp3d.training.trainer import Trainer

#: Caps of the numeric flags, checked at parse time (before any set-up or allocation): a batch beyond
#: this cannot fit any accelerator at the paper's sizes, a step count beyond it is a typo, and the
#: identities are drawn from the configurations' training seed range, [0, 1,000,000).
MAX_BATCH = 4096
MAX_STEPS = 10**9
MAX_IDENTITIES = 1_000_000

#: ``--help``'s description (``python -m lp3d.train`` and ``lp3d train``).
DESCRIPTION = "Distil a teacher into the LP3D triplane encoder (paper §3.2)."


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The training options, shared by ``python -m lp3d.train`` and ``lp3d train``."""
    p.add_argument(
        "--config",
        choices=sorted(TRAIN_CONFIGS),
        help="named configuration (default tiny; on --resume, the checkpoint's)",
    )
    p.add_argument("--teacher", choices=TEACHERS, default=None, help="teacher (default procedural)")
    p.add_argument(
        "--teacher-pkl",
        help="EG3D generator pickle for --teacher eg3d (remembered on --resume)",
    )
    p.add_argument(
        "--eg3d-source",
        help="NVlabs/eg3d's source, to unpickle the generator: the repository root or its inner eg3d/ "
        "folder (the one holding torch_utils/, dnnlib/ and training/); not needed when those are "
        "importable already (remembered on --resume)",
    )
    p.add_argument(
        "--eg3d-conditioning",
        choices=("gen_videos", "gen_samples"),
        help="whose conditioning camera the EG3D mapping gets: gen_videos.py's (LookAtPoseSampler(3.14/2, "
        "3.14/2), focal 4.2647; default) or gen_samples.py's (exactly frontal, focal 4.26339)",
    )
    p.add_argument("--out", default=None, help="run directory (default runs/<config>)")
    p.add_argument(
        "--max-steps",
        type=int_in(1, MAX_STEPS),
        help="stop at this global step (default: config)",
    )
    p.add_argument(
        "--batch",
        type=int_in(1, MAX_BATCH),
        help=f"batch size, global over all processes (overrides the config; at most {MAX_BATCH})",
    )
    p.add_argument(
        "--total-steps",
        type=int_in(1, MAX_STEPS),
        help="rescale the config's schedule (stage boundaries keep the paper's proportions) to this "
        "length; with --resume, lengthen the run's learning-rate schedule to it",
    )
    p.add_argument("--resume", default=None, help="checkpoint file or run directory to continue from")
    p.add_argument(
        "--perceptual",
        choices=PERCEPTUAL_KINDS,
        help="perceptual loss (default: the config's; lpips needs backbone weights on disk)",
    )
    p.add_argument("--lpips-weights", default=None, help="torchvision VGG16/AlexNet state dict for LPIPS")
    p.add_argument(
        "--data-cache",
        help="folder of the CPU recipe's cached synthetic datasets (default $LP3D_DATA_CACHE, "
        "$LP3D_CACHE/datasets or ~/.cache/lp3d/datasets)",
    )
    p.add_argument(
        "--dataset-identities",
        type=int_in(1, MAX_IDENTITIES),
        help="identities in the CPU recipe's synthetic dataset (overrides the config)",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int_in(1, MAX_STEPS),
        help="write a checkpoint every N steps (default: the config's; may change on --resume)",
    )
    p.add_argument(
        "--device",
        default="auto",
        help="cpu, cuda, cuda:N or auto; under torchrun each process takes cuda:LOCAL_RANK (cuda:N is "
        "refused) or the CPU",
    )
    p.add_argument(
        "--dist-timeout",
        type=float,
        default=60.0,
        metavar="MINUTES",
        help="under torchrun, how long a process waits for the others at a collective call (default 60; "
        "it must cover rank 0 synthesising a missing dataset)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser(prog: str = "python -m lp3d.train") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=run_cli)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m lp3d.train`` (an alias of ``lp3d train``); the exit status is :mod:`lp3d.errors`'
    policy: 0 done, 1 an error (printed as one line), 2 a usage error, 130 interrupted."""
    return run_command(build_parser(), argv)


def run_cli(args: argparse.Namespace) -> int:
    """Train with parsed :func:`add_arguments` options; returns the exit status."""
    try:
        return _main(args)
    finally:
        distributed.shutdown()  # leaves torchrun's process group (a no-op for one process)


def _error(e: BaseException | str) -> None:
    """Print an error; every process does (one rank may fail alone), and under torchrun names its rank."""
    where = f" (rank {distributed.rank()})" if distributed.world_size() > 1 else ""
    print(f"error{where}: {renderer_setup_error(str(e)) or e}", file=sys.stderr)


def _main(args: argparse.Namespace) -> int:
    try:
        if not (math.isfinite(args.dist_timeout) and args.dist_timeout > 0):
            raise ValueError(f"--dist-timeout must be a positive number of minutes, got {args.dist_timeout}")
        device = distributed.setup(args.device, timeout_minutes=args.dist_timeout).device
        ckpt = load_shared_checkpoint(args.resume) if args.resume else None
        cfg, teacher_name, out = _run_of(args, ckpt)
        cfg = _with_overrides(args, cfg, ckpt)
        perceptual = build_perceptual(
            cfg.perceptual, lpips_net=cfg.lpips_net, lpips_weights=args.lpips_weights
        )
        if perceptual is not None:
            perceptual = perceptual.to(device)
        targs = _teacher_args(args, ckpt, teacher_name)
        teacher = build_teacher(
            teacher_name,
            triplane_resolution=cfg.triplane_resolution,
            teacher_pkl=targs["teacher_pkl"],
            eg3d_source=targs["eg3d_source"],
            conditioning=targs["conditioning"],  # type: ignore[arg-type]
            device=device,
        )
        trainer = Trainer(
            cfg,
            out,
            teacher=teacher,
            teacher_name=teacher_name,
            perceptual=perceptual,
            device=device,
            resume=ckpt["path"] if ckpt is not None else None,
            progress=not args.no_progress,
            data_cache=args.data_cache,
            teacher_args=targs,
        )
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        _error(e)
        return EXIT_ERROR
    distributed.note(
        f"training {cfg.name!r} on {device} with the {teacher_name} teacher, batch {cfg.batch_size}, "
        f"from step {trainer.step} to {args.max_steps or cfg.total_steps}; run directory {out}"
    )
    return _train(trainer, args.max_steps, out)


def _run_of(args: argparse.Namespace, ckpt: dict[str, Any] | None) -> tuple[TrainConfig, str, Path]:
    """``(config, teacher name, run directory)``: the checkpoint's on ``--resume``, else the options'."""
    if ckpt is not None:
        cfg: TrainConfig = ckpt["train_config"]
        if args.config is not None and args.config != cfg.name:
            raise CheckpointError(
                f"--resume {args.resume}: the checkpoint was trained with configuration {cfg.name!r}, "
                f"not {args.config!r}; omit --config to resume it"
            )
        teacher_name = args.teacher or ckpt["teacher"]
        out = Path(args.out) if args.out else Path(ckpt["path"]).parent.parent
    else:
        cfg = TRAIN_CONFIGS[args.config or "tiny"]
        teacher_name = args.teacher or "procedural"
        out = Path(args.out) if args.out else Path("runs") / cfg.name
    return cfg, teacher_name, out


def _with_overrides(args: argparse.Namespace, cfg: TrainConfig, ckpt: dict[str, Any] | None) -> TrainConfig:
    """``cfg`` with the options that override it (``--batch``, ``--total-steps``, ...); a resumed run
    may not change its schedule or dataset."""
    if args.batch is not None:
        cfg = dataclasses.replace(cfg, batch_size=args.batch)
    if args.total_steps is not None and args.total_steps < 1:
        raise ValueError(f"--total-steps must be >= 1, got {args.total_steps}")
    if args.total_steps is not None and ckpt is not None and args.total_steps != cfg.total_steps:
        cfg = extended_schedule(cfg, args.total_steps)
        distributed.note(f"note: schedule extended to {args.total_steps} steps")
    elif args.total_steps is not None:
        cfg = dataclasses.replace(cfg, **scaled_schedule(args.total_steps, cfg))
    if args.perceptual is not None:
        cfg = dataclasses.replace(cfg, perceptual=args.perceptual)
    if args.checkpoint_every is not None:
        if args.checkpoint_every < 1:
            raise ValueError(f"--checkpoint-every must be >= 1, got {args.checkpoint_every}")
        cfg = dataclasses.replace(cfg, checkpoint_every=args.checkpoint_every)
    if args.dataset_identities is not None:
        if ckpt is not None and args.dataset_identities != cfg.dataset_identities:
            raise CheckpointError(
                f"--dataset-identities {args.dataset_identities}: the checkpoint was trained on "
                f"{cfg.dataset_identities}; a resumed run keeps its dataset"
            )
        cfg = dataclasses.replace(cfg, dataset_identities=args.dataset_identities)
    return cfg


def _teacher_args(
    args: argparse.Namespace, ckpt: dict[str, Any] | None, teacher_name: str
) -> dict[str, str | None]:
    """How to build the teacher: the options, else (for the same teacher) the run's recorded ones; a
    resumed run may not change the EG3D conditioning."""
    targs = resolve_teacher_args(
        ckpt if ckpt is not None and teacher_name == ckpt["teacher"] else None,
        teacher_pkl=args.teacher_pkl,
        eg3d_source=args.eg3d_source,
        conditioning=args.eg3d_conditioning,
    )
    recorded = resolve_teacher_args(ckpt) if ckpt is not None else None
    if recorded is not None and recordable_teacher_args(targs) != recorded:  # recorded paths are absolute
        if targs["conditioning"] != recorded["conditioning"]:
            raise CheckpointError(
                f"--eg3d-conditioning {targs['conditioning']}: the run was trained with "
                f"{recorded['conditioning']!r}; a resumed run keeps its teacher"
            )
        distributed.note(f"note: teacher arguments differ from the run's recorded ones: {targs}")
    return targs


def _train(trainer: Trainer, max_steps: int | None, out: Path) -> int:
    """Run the trainer to ``max_steps``; the exit status, with where to continue an interrupted run."""
    try:
        trainer.train(max_steps)
    except NonFiniteError as e:
        _error(e)
        return EXIT_ERROR
    except KeyboardInterrupt:
        distributed.note(f"aborted; the last checkpoint is {latest_checkpoint(out)}")
        return EXIT_INTERRUPTED
    if trainer.interrupted:
        last = latest_checkpoint(out) if trainer.is_main else None
        distributed.note(f"interrupted at step {trainer.step}; saved {last}; continue with --resume {out}")
        return EXIT_INTERRUPTED
    if trainer.is_main:
        print(f"done at step {trainer.step}; checkpoint {latest_checkpoint(out)}", file=sys.stderr)
    return 0
