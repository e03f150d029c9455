"""``lp3d serve``'s lifted photos, kept in memory for their downloads, and their refinement
(``--refine`` of ``lp3d encode``, :func:`lp3d.lift.refine.refine`) run one at a time on a thread of
its own, with progress the page polls."""

from __future__ import annotations

import secrets
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np

from lp3d.lift.refine_settings import MAX_STEPS, RefineSettings
from lp3d.serve.lifting import PhotoResult

__all__ = ["PhotoStore", "RefineJobs", "torch_available"]


class PhotoStore:
    """The last ``keep`` lifted photos by random id (older ones are forgotten); thread-safe."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self._items: OrderedDict[str, PhotoResult] = OrderedDict()
        self._lock = threading.Lock()

    def add(self, result: PhotoResult) -> str:
        pid = secrets.token_hex(8)
        with self._lock:
            self._items[pid] = result
            while len(self._items) > self.keep:
                self._items.popitem(last=False)
        return pid

    def get(self, pid: str) -> PhotoResult | None:
        with self._lock:
            return self._items.get(pid)

    def replace(self, pid: str, result: PhotoResult) -> None:
        with self._lock:
            if pid in self._items:
                self._items[pid] = result


def torch_available() -> bool:
    """Whether PyTorch is installed (found, not imported: importing it takes seconds)."""
    import importlib.util

    return importlib.util.find_spec("torch") is not None


class RefineJobs:
    """Refinement of stored photos, one at a time (each uses every core); the refined triplane replaces
    the photo's in the store when it is done."""

    def __init__(self, store: PhotoStore, package: Any) -> None:
        self.store = store
        self.package = package
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lp3d-refine")
        self._lock = threading.Lock()
        self._jobs: dict[str, dict[str, Any]] = {}
        self._superres: Any = None

    def progress(self, pid: str) -> dict[str, Any]:
        """``{"state": "none" | "queued" | "running" | "done" | "failed", "step", "total", ...}``."""
        with self._lock:
            return dict(self._jobs.get(pid, {"state": "none", "step": 0, "total": 0}))

    def start(self, pid: str, result: PhotoResult, steps: int) -> None:
        if not 1 <= steps <= MAX_STEPS:
            raise ValueError(f"steps: 1 to {MAX_STEPS}")
        settings = RefineSettings(steps=steps)
        with self._lock:
            if self._jobs.get(pid, {}).get("state") in ("queued", "running"):
                raise ValueError("this photo is already being refined")
            total = settings.total_steps(result.pose is not None)
            self._jobs[pid] = {"state": "queued", "step": 0, "total": total, "steps": steps}
        self._pool.submit(self._run, pid, result, settings)

    def _update(self, pid: str, **values: Any) -> None:
        with self._lock:
            self._jobs[pid].update(values)

    def _run(self, pid: str, result: PhotoResult, settings: RefineSettings) -> None:
        from lp3d.lift.refine import refine, superres_module

        self._update(pid, state="running")
        t0 = time.perf_counter()
        try:
            has_superres = self.package.superres is not None
            if self._superres is None and settings.superres_steps(has_superres) > 0:
                self._superres = superres_module(self.package)
            start = replace(result.triplane, planes=result.triplane.planes.astype(np.float32))
            done = [0]

            def step() -> None:
                done[0] += 1
                self._update(pid, step=done[0])

            superres = self._superres if settings.superres_steps(has_superres) > 0 else None
            fitted = refine(start, result.crop, settings, pose=result.pose, superres=superres, on_step=step)
            tri = replace(fitted.triplane, planes=fitted.triplane.planes.astype(np.float16))
            if not np.isfinite(tri.planes).all():
                raise ValueError("the refined planes exceed float16's range")
            self.store.replace(pid, replace(result, triplane=tri, pose=(fitted.yaw_deg, fitted.pitch_deg)))
            self._update(
                pid,
                state="done",
                seconds=round(time.perf_counter() - t0, 2),
                psnr_before=round(fitted.psnr_before, 2),
                psnr_after=round(fitted.psnr_after, 2),
            )
        except Exception as e:  # reported to the page, which shows it; the server goes on
            self._update(pid, state="failed", error=f"{type(e).__name__}: {e}"[:300])
