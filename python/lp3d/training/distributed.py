"""Multi-process training on torch's own engine (``torch.distributed``, started by ``torchrun``).

``torchrun --nproc-per-node N -m lp3d.train ...`` starts N copies of the trainer with ``WORLD_SIZE``,
``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` in their environment;
:func:`setup` reads them, joins the process group (NCCL on GPUs, gloo on the CPU) and gives each
rank its device (``cuda:LOCAL_RANK``). Without those variables everything here is a no-op for one
process, so the single-process trainer runs exactly as before.

How :mod:`lp3d.train` uses it (data parallel, the gradient average done by hand rather than by
``DistributedDataParallel``: the student is called through ``encode``/``render`` rather than
``forward``, parts of it are frozen and unfrozen between stages, and the discriminator's lazy R1
takes a double backward, none of which DDP's hooks support):

* every rank draws the *global* batch from the same data stream and keeps its rows
  ``rank, rank + W, rank + 2W, ...`` (:func:`shard`), so the ranks' identities are disjoint and
  together are exactly the single-process batch;
* after each backward pass the gradients are averaged over the ranks (:func:`average_gradients`),
  so every rank takes the same optimiser step;
* rank 0 alone writes the run directory; the others wait at the next collective call.
"""

from __future__ import annotations

import datetime
import os
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
import torch.distributed as tdist
from torch import Tensor, nn

__all__ = [
    "DistributedSetupError",
    "World",
    "all_gather_objects",
    "any_rank",
    "average_gradients",
    "backend",
    "barrier",
    "broadcast_module",
    "broadcast_object",
    "broadcast_tensor",
    "in_turn",
    "is_main",
    "local_rank",
    "mean_over_ranks",
    "note",
    "rank",
    "setup",
    "shard",
    "shutdown",
    "world_size",
]

T = TypeVar("T")

#: The environment ``torchrun`` gives each process.
ENV_VARS = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
#: Gradients are averaged in flat buckets of at most this many elements (one collective call each).
BUCKET_ELEMENTS = 1 << 24


class DistributedSetupError(RuntimeError):
    """The torchrun environment is incomplete or does not fit the requested device."""


@dataclass(frozen=True)
class World:
    """Where this process stands: ``rank`` of ``size`` processes, ``local_rank`` on its machine."""

    size: int
    rank: int
    local_rank: int
    backend: str | None
    device: torch.device


def _env_int(name: str) -> int:
    raw = os.environ.get(name, "")
    try:
        value = int(raw)
    except ValueError:
        raise DistributedSetupError(f"environment variable {name}={raw!r} is not an integer") from None
    if value < 0:
        raise DistributedSetupError(f"environment variable {name}={value} is negative")
    return value


def setup(device: str = "auto", *, timeout_minutes: float = 60.0) -> World:
    """Join torchrun's process group when this process was started by torchrun with more than one
    process, and choose the device.

    ``device``: ``auto`` (CUDA when available), ``cpu``, ``cuda`` or ``cuda:N``. Under torchrun each
    rank takes ``cuda:LOCAL_RANK`` and an explicit ``cuda:N`` is refused (every rank would share one
    GPU). The backend is NCCL for CUDA and gloo for the CPU. ``timeout_minutes`` bounds how long a
    rank waits for the others at a collective call (rank 0 alone synthesises the CPU recipe's dataset
    and writes checkpoints, samples and the held-out curve while the others wait).

    Raises:
        DistributedSetupError: a partial torchrun environment, a rank outside the world, ``cuda:N``
            under torchrun, or CUDA asked for where there is none.
    """
    present = [v for v in ENV_VARS if v in os.environ]
    if "WORLD_SIZE" not in os.environ or _env_int("WORLD_SIZE") <= 1:
        return World(1, 0, 0, None, _single_device(device))
    missing = [v for v in ENV_VARS if v not in present]
    if missing:
        raise DistributedSetupError(
            f"WORLD_SIZE is set but {', '.join(missing)} not: start distributed training with torchrun "
            "(torchrun --nproc-per-node N -m lp3d.train ...)"
        )
    size, rank_, local = _env_int("WORLD_SIZE"), _env_int("RANK"), _env_int("LOCAL_RANK")
    if rank_ >= size:
        raise DistributedSetupError(f"RANK={rank_} is outside WORLD_SIZE={size}")
    if device.startswith("cuda:"):
        raise DistributedSetupError(
            f"--device {device}: under torchrun each rank uses cuda:LOCAL_RANK; pass --device cuda or auto "
            "(and CUDA_VISIBLE_DEVICES to choose the GPUs)"
        )
    if device == "auto":
        use_cuda = torch.cuda.is_available()
    elif device == "cuda":
        if not torch.cuda.is_available():
            raise DistributedSetupError("--device cuda: CUDA is not available here (use --device cpu)")
        use_cuda = True
    elif device == "cpu":
        use_cuda = False
    else:
        raise DistributedSetupError(f"--device {device!r}: under torchrun choose auto, cuda or cpu")
    if use_cuda:
        if local >= torch.cuda.device_count():
            raise DistributedSetupError(
                f"LOCAL_RANK={local} but only {torch.cuda.device_count()} GPU(s) are visible: start at most "
                "that many processes per node"
            )
        dev = torch.device("cuda", local)
        torch.cuda.set_device(dev)
        backend = "nccl"
    else:
        dev, backend = torch.device("cpu"), "gloo"
    tdist.init_process_group(backend, timeout=datetime.timedelta(minutes=timeout_minutes))
    return World(size, rank_, local, backend, dev)


def _single_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as e:
        raise DistributedSetupError(f"--device {name!r}: {e}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DistributedSetupError("--device cuda: CUDA is not available here (use --device cpu)")
    return dev


def shutdown() -> None:
    """Leave the process group (a no-op for one process)."""
    if tdist.is_available() and tdist.is_initialized():
        tdist.destroy_process_group()


def _active() -> bool:
    return tdist.is_available() and tdist.is_initialized() and tdist.get_world_size() > 1


def world_size() -> int:
    return tdist.get_world_size() if _active() else 1


def backend() -> str | None:
    """The process group's backend (``nccl``, ``gloo``), or None for one process."""
    return str(tdist.get_backend()) if _active() else None


def rank() -> int:
    return tdist.get_rank() if _active() else 0


def local_rank() -> int:
    return int(os.environ.get("LOCAL_RANK", "0")) if _active() else 0


def is_main() -> bool:
    """Rank 0, the one process that writes the run directory."""
    return rank() == 0


def barrier() -> None:
    if _active():
        tdist.barrier()


def shard(x: T, *, rank_: int | None = None, size: int | None = None) -> T:
    """This rank's rows ``rank, rank + W, ...`` of a global batch (a tensor, array or list, first
    axis). Strided rather than contiguous so that the discriminator's minibatch-stddev groups, which
    are strided too, hold the same samples on a rank as in one process whenever the per-rank batch is
    a multiple of the group size (see ``docs/training.md``)."""
    r = rank() if rank_ is None else rank_
    w = world_size() if size is None else size
    if w == 1:
        return x
    return x[r::w]  # type: ignore[index]


def in_turn(fn: Callable[[], T]) -> T:
    """``fn()`` on every rank, rank 0 first, then local rank 0 of each other machine, then the rest,
    with barriers between: for work that fills a cache the later ones then read (the CPU recipe's
    dataset), so no two processes of a machine write the same files at once."""
    if not _active():
        return fn()
    turn = 0 if rank() == 0 else 1 if local_rank() == 0 else 2
    result: Any = None
    for stage in range(3):
        if stage == turn:
            result = fn()
        tdist.barrier()
    return result


def _buckets(tensors: list[Tensor]) -> Iterable[list[Tensor]]:
    """Tensors grouped by dtype and device into lists of at most :data:`BUCKET_ELEMENTS` elements."""
    groups: dict[tuple[torch.dtype, torch.device], list[Tensor]] = {}
    for t in tensors:
        groups.setdefault((t.dtype, t.device), []).append(t)
    for group in groups.values():
        bucket: list[Tensor] = []
        count = 0
        for t in group:
            if bucket and count + t.numel() > BUCKET_ELEMENTS:
                yield bucket
                bucket, count = [], 0
            bucket.append(t)
            count += t.numel()
        if bucket:
            yield bucket


def average_gradients(parameters: Iterable[nn.Parameter]) -> None:
    """Replace each parameter's ``.grad`` by its mean over the ranks (in place; a no-op for one
    process). Parameters without a gradient are left out; every rank must have gradients for the same
    parameters, which holds because all ranks run the same code path on the same step."""
    if not _active():
        return
    grads = [p.grad for p in parameters if p.grad is not None]
    w = tdist.get_world_size()
    for bucket in _buckets(grads):
        flat = torch.cat([g.reshape(-1) for g in bucket])
        tdist.all_reduce(flat)
        flat /= w
        offset = 0
        for g in bucket:
            n = g.numel()
            g.copy_(flat[offset : offset + n].view_as(g))
            offset += n


def mean_over_ranks(values: dict[str, float], device: torch.device) -> dict[str, float]:
    """The mean of each value over the ranks (the same keys on every rank), in one collective call."""
    if not _active() or not values:
        return dict(values)
    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    tdist.all_reduce(t)
    t /= tdist.get_world_size()
    return dict(zip(keys, t.tolist(), strict=True))


def any_rank(flag: bool, device: torch.device) -> bool:
    """Whether ``flag`` is true on any rank (one collective call; ``flag`` itself for one process)."""
    if not _active():
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    tdist.all_reduce(t, op=tdist.ReduceOp.MAX)
    return bool(t.item() > 0)


def broadcast_tensor(t: Tensor, src: int = 0) -> None:
    """Overwrite ``t`` (in place) with rank ``src``'s values."""
    if _active():
        tdist.broadcast(t.data, src)


@torch.no_grad()
def broadcast_module(module: nn.Module, src: int = 0) -> None:
    """Give every rank rank ``src``'s parameters and buffers."""
    if not _active():
        return
    for t in [*module.parameters(), *module.buffers()]:
        tdist.broadcast(t.data, src)


def broadcast_object(obj: T, src: int = 0) -> T:
    """Rank ``src``'s ``obj`` (picklable) on every rank."""
    if not _active():
        return obj
    box = [obj]
    tdist.broadcast_object_list(box, src)
    return box[0]


def all_gather_objects(obj: T) -> list[T]:
    """Every rank's ``obj`` (picklable), in rank order, on every rank."""
    if not _active():
        return [obj]
    out: list[Any] = [None] * tdist.get_world_size()
    tdist.all_gather_object(out, obj)
    return out


def note(message: str) -> None:
    """Print ``message`` to stderr on rank 0 only."""
    if is_main():
        print(message, file=sys.stderr)
