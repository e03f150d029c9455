"""A small baked field on disk and hand-made variants of its file, for the hostile-input tests and the
fuzzer of :func:`lp3d.render.baked.load_baked` (``tests/robustness/test_hostile_baked.py``,
``tests/robustness/test_baked_fuzz.py``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from support.triplane_files import Entry, build_zip, npy, npy_of

#: The field's sub-cells per cell edge and its occupancy grid side: a 16² sphere at G 8, k 2
#: (432 bricks, a 100 KB file, 1 ms a load on lavapipe).
K, G = 2, 8


def small_baked(folder: Path) -> tuple[Any, Path]:
    """``(triplane, path)``: an ``lp3d_render.Triplane`` (a small sphere with its occupancy grid) and
    its baked field saved at ``folder/sphere.baked.npz``."""
    import lp3d_render
    from lp3d.render.baked import save_baked
    from lp3d.render.sample_scenes import coloured_sphere

    tri = coloured_sphere(size=16, radius=0.3)
    native = dataclasses.replace(tri, occupancy=tri.to_native().bake_occupancy(G)).to_native()
    field = lp3d_render.bake(native, subdivisions=K, occupancy_epsilon=1e-4, depth_resolution=12)
    return native, save_baked(folder / "sphere.baked.npz", field, native)


def arrays_of(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a (valid) baked-field file."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def baked_bytes(arrays: dict[str, np.ndarray | bytes]) -> bytes:
    """An uncompressed ``.npz`` of ``arrays``; a ``bytes`` value is the entry's ``.npy`` as it is."""
    return build_zip([Entry(f"{k}.npy", v if isinstance(v, bytes) else npy_of(v)) for k, v in arrays.items()])


def claiming(shape: str, descr: str = "<f2", body: bytes = b"\0" * 64) -> bytes:
    """A ``.npy`` whose header claims ``shape`` of ``descr`` over a short body."""
    return npy(f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}", body)
