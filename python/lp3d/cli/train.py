"""``lp3d train`` (and ``python -m lp3d.train``): distil a teacher into the triplane encoder with
:func:`lp3d.training.train`.

The library needs torch (the ``train`` extra), so it is imported only when this subcommand is parsed
or run. Under torchrun every process runs this command; errors name the rank that raised them."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence

from lp3d.errors import EXIT_ERROR, EXIT_INTERRUPTED, int_in, renderer_setup_error, run_command

HELP = "distil a teacher into the encoder (python -m lp3d.train; needs torch)"
#: This subcommand's options import torch: the top-level parser adds them only when it is named.
LAZY = True
DESCRIPTION = "Distil a teacher into the LP3D triplane encoder (paper §3.2)."

#: Caps of the numeric flags, checked at parse time (before any set-up or allocation): a batch beyond
#: this cannot fit any accelerator at the paper's sizes, a step count beyond it is a typo, and the
#: identities are drawn from the configurations' training seed range, [0, 1,000,000).
MAX_BATCH = 4096
MAX_STEPS = 10**9
MAX_IDENTITIES = 1_000_000


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The training options, shared by ``python -m lp3d.train`` and ``lp3d train``."""
    from lp3d.training.config import TRAIN_CONFIGS
    from lp3d.training.losses import PERCEPTUAL_KINDS

    p.add_argument(
        "--config",
        choices=sorted(TRAIN_CONFIGS),
        help="named configuration (default tiny; on --resume, the checkpoint's)",
    )
    _add_teacher_arguments(p)
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
    p.add_argument(
        "--ray-from",
        type=int_in(0, MAX_STEPS),
        help="CPU recipe: add the RGB loss on random rays from this step on (default: the config's; "
        "with --resume, any step the run has not taken yet)",
    )
    p.add_argument("--resume", default=None, help="checkpoint file or run directory to continue from")
    _add_warm_start_arguments(p)
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


def _add_warm_start_arguments(p: argparse.ArgumentParser) -> None:
    """``--init-from`` and ``--lr-scale``: a new run that fine-tunes trained weights."""
    p.add_argument(
        "--init-from",
        default=None,
        metavar="WEIGHTS",
        help="a new run's encoder starts from these weights (a model package .pt or a run checkpoint); "
        "what the configuration adds starts at zero (docs/training.md, 'Starting from trained weights')",
    )
    p.add_argument(
        "--lr-scale",
        type=float,
        help="multiply the student's learning rates (a new run; e.g. 0.2 to fine-tune after --init-from)",
    )


def _add_teacher_arguments(p: argparse.ArgumentParser) -> None:
    """Which teacher, and for EG3D where its pickle and source are."""
    from lp3d.training.teacher_factory import TEACHERS

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


def run(args: argparse.Namespace) -> int:
    """Train with parsed :func:`add_arguments` options; returns the exit status."""
    from lp3d.training import distributed, train

    if not (math.isfinite(args.dist_timeout) and args.dist_timeout > 0):
        _error(f"--dist-timeout must be a positive number of minutes, got {args.dist_timeout}")
        return EXIT_ERROR
    try:
        result = train(
            args.config,
            out=args.out,
            resume=args.resume,
            max_steps=args.max_steps,
            teacher=args.teacher,
            teacher_pkl=args.teacher_pkl,
            eg3d_source=args.eg3d_source,
            eg3d_conditioning=args.eg3d_conditioning,
            batch=args.batch,
            total_steps=args.total_steps,
            ray_from=args.ray_from,
            perceptual=args.perceptual,
            lpips_weights=args.lpips_weights,
            data_cache=args.data_cache,
            dataset_identities=args.dataset_identities,
            lr_scale=args.lr_scale,
            checkpoint_every=args.checkpoint_every,
            device=args.device,
            dist_timeout_minutes=args.dist_timeout,
            progress=not args.no_progress,
            init_from=args.init_from,
        )
    except (ValueError, RuntimeError, FileNotFoundError) as e:  # NonFiniteError is a ValueError
        _error(e)
        return EXIT_ERROR
    except KeyboardInterrupt:  # train() has said which checkpoint to continue from
        return EXIT_INTERRUPTED
    if result.interrupted:  # a SIGTERM: the run saved a checkpoint and stopped
        saved = f"saved {result.checkpoint}; continue with --resume {result.out}"
        distributed.note(f"interrupted at step {result.step}; {saved}")
        return EXIT_INTERRUPTED
    if result.checkpoint is not None:  # rank 0's line
        print(f"done at step {result.step}; checkpoint {result.checkpoint}", file=sys.stderr)
    return 0


def _error(e: BaseException | str) -> None:
    """Print an error; every process does (one rank may fail alone), and under torchrun names its rank."""
    from lp3d.training import distributed

    where = f" (rank {distributed.rank()})" if distributed.world_size() > 1 else ""
    print(f"error{where}: {renderer_setup_error(str(e)) or e}", file=sys.stderr)


def build_parser(prog: str = "python -m lp3d.train") -> argparse.ArgumentParser:
    """This command's parser on its own (as ``lp3d-view``'s is)."""
    from lp3d.cli import standalone_parser

    return standalone_parser(sys.modules[__name__], prog)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m lp3d.train`` (the same as ``lp3d train``); the exit status is :mod:`lp3d.errors`'
    policy: 0 done, 1 an error (printed as one line), 2 a usage error, 130 interrupted."""
    return run_command(build_parser(), None if argv is None else list(argv))
