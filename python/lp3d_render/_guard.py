"""Checks made in Python before a call reaches the GPU: a process forked after its parent used the GPU,
a batch whose outputs cannot fit in memory, and a file-size limit the driver's memory cannot live
under, or an address-space limit (``ulimit -v``) it cannot start under. None would otherwise come
back as an error: the device and its threads do not survive ``fork`` (the call hangs), a failed
allocation of the outputs aborts the process, a driver that keeps device memory in files (Mesa's
lavapipe) dies of SIGBUS when one cannot grow, and one whose mappings fail dies of SIGSEGV."""

from __future__ import annotations

import errno
import functools
import os
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from lp3d_render import _lp3d_render as _native

__all__ = [
    "adapter_info",
    "attach_baked",
    "bake",
    "last_frame_device_bytes",
    "output_bytes",
    "render",
]
__all__ += ["view"]

_F = TypeVar("_F", bound=Callable[..., Any])

#: The process that first called into the GPU; a process whose pid differs inherited the device by fork.
_gpu_pid: int | None = None

#: Outputs as ``render`` returns them: name -> channels per pixel.
_CHANNELS = {"features": 32, "rgb": 3, "depth": 1, "weights_sum": 1}


#: Mesa's software Vulkan driver keeps device memory in memory-backed files ("allocation fd") grown
#: in blocks of 64 MiB; under a smaller file-size limit (``ulimit -f``) growing one fails with EFBIG,
#: the driver does not check, and its next touch of the memory kills the process with SIGBUS.
_DRIVER_FILE_BYTES = (64 << 20) + (1 << 20)


def _check_file_size_limit(need: int = 0) -> None:
    """An OSError (EFBIG, "File too large", as a write over the limit reports it) when this process's
    file-size limit is below what the driver's memory files need (``need``: a render's outputs)."""
    try:
        import resource
    except ImportError:  # not on this platform: no such limit
        return
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    need = max(need, _DRIVER_FILE_BYTES)
    if soft != resource.RLIM_INFINITY and soft < need:
        e = OSError(
            f"File too large: the GPU driver keeps its memory in files of up to {need >> 20} MiB, over "
            f"this process's file-size limit (ulimit -f) of {soft} bytes; raise the limit"
        )
        e.errno = errno.EFBIG
        raise e


#: Address space the GPU device maps when it is created (Mesa's lavapipe: its LLVM JIT, threads and
#: first memory files), as measured there. A mapping that fails under ``ulimit -v`` is not checked by
#: the driver: the process dies of SIGSEGV.
_DEVICE_ADDRESS_BYTES = 800 << 20


def _address_space_left() -> int | None:
    """Bytes this process may still map under its address-space limit (``ulimit -v``), or None when
    it has none (or the platform does not say). ``lp3d.errors.address_space_left`` is its twin for
    the command line (lp3d_render does not import lp3d)."""
    try:
        import resource
    except ImportError:
        return None
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/statm") as f:
            mapped = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None
    return soft - mapped


def _check_address_space(need: int = 0) -> None:
    """An OSError (ENOMEM) when the address-space limit leaves less than the device (at the first
    call) and ``need`` (a render's outputs) take."""
    left = _address_space_left()
    need += _DEVICE_ADDRESS_BYTES if _gpu_pid is None else 0
    if left is not None and left < need:
        e = OSError(
            f"Cannot allocate memory: the GPU driver needs about {need >> 20} MiB of address space, and "
            f"this process's address-space limit (ulimit -v) leaves {max(left, 0) >> 20} MiB; raise the "
            "limit"
        )
        e.errno = errno.ENOMEM
        raise e


def _check_process() -> None:
    _check_file_size_limit()
    _check_address_space()
    global _gpu_pid
    pid = os.getpid()
    if _gpu_pid is None:
        _gpu_pid = pid  # set before the call: it may create the device even if it fails
    elif _gpu_pid != pid:
        raise RuntimeError(
            f"lp3d_render: this process (pid {pid}) was forked from process {_gpu_pid} after that one "
            "used the GPU, and a GPU device does not survive fork (the call would hang). Start worker "
            "processes with the 'spawn' or 'forkserver' method (multiprocessing.get_context('spawn'); "
            "for a PyTorch DataLoader, multiprocessing_context='spawn'), or render only in the parent"
        )


def _gpu_call(func: _F) -> _F:
    @functools.wraps(func)
    def call(*args: Any, **kwargs: Any) -> Any:
        _check_process()
        return func(*args, **kwargs)

    return call  # type: ignore[return-value]


def output_bytes(n_cameras: int, resolution: int, outputs: list[str] | None) -> int:
    """Bytes of memory a render's outputs take at their peak: the renderer's float32 buffers (features,
    or the 3 RGB channels alone, plus depth and weights_sum) and the arrays returned."""
    names = set(_CHANNELS) if outputs is None else set(outputs) & set(_CHANNELS)
    channels = 32 if "features" in names else 3 if "rgb" in names else 0
    rust = channels + 2 + (3 if "rgb" in names else 0)
    returned = sum(_CHANNELS[n] for n in names)
    return 4 * n_cameras * resolution * resolution * (rust + returned)


def _memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not on this platform
        return None


def _check_size(camera: Any, resolution: Any, outputs: Any) -> None:
    """Refuse a batch whose outputs need more memory than the machine has, before the renderer tries
    to allocate it. Arguments of the wrong type are left for the renderer to name."""
    if outputs is None:
        names: list[str] | None = None
    elif isinstance(outputs, list | tuple) and all(isinstance(n, str) for n in outputs):
        names = list(outputs)
    else:  # a generator (not to be consumed here) or wrong types
        return
    try:
        shape = np.shape(camera)
    except Exception:  # anything odd is the renderer's to report
        return
    r = int(resolution) if isinstance(resolution, int | np.integer) else None
    if r is None or not 1 <= r <= _native.MAX_RESOLUTION or len(shape) not in (1, 2):
        return  # the renderer names a bad resolution or camera shape
    n = shape[0] if len(shape) == 2 else 1
    need, have = output_bytes(n, r, names), _memory_bytes()
    _check_file_size_limit(need)
    _check_address_space(need)
    if have is not None and need > have:
        gib = 1 << 30
        raise ValueError(
            f"camera: a batch of {n} cameras at {r}² needs {need / gib:.1f} GiB of memory for its outputs, "
            f"more than the system's {have / gib:.1f} GiB; render fewer cameras per call (or ask for "
            "fewer outputs, such as outputs=['rgb'])"
        )


@functools.wraps(_native.render)
def render(triplane: Any, camera: Any, resolution: Any = 128, *args: Any, **kwargs: Any) -> Any:
    _check_size(camera, resolution, kwargs.get("outputs", args[4] if len(args) > 4 else None))
    _check_process()
    return _native.render(triplane, camera, resolution, *args, **kwargs)


adapter_info = _gpu_call(_native.adapter_info)
bake = _gpu_call(_native.bake)
attach_baked = _gpu_call(_native.attach_baked)
last_frame_device_bytes = _gpu_call(_native.last_frame_device_bytes)
# The viewer makes its own device (eframe's), on the same driver: the same limit kills it.
view = _gpu_call(_native.view)
