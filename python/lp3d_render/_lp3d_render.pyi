"""Type stubs for the native module; tests/project/test_stubs_and_packaging.py checks them against the
runtime."""

from collections.abc import Callable, Iterable, Sequence
from os import PathLike
from typing import Any

import numpy as np
import numpy.typing as npt

MAX_RESOLUTION: int
MAX_SAMPLES: int
BAKED_SUBDIVISIONS: int
BAKED_FINE_SUBDIVISIONS: int
BAKED_OCCUPANCY_EPSILON: float
PLANE_AXES: list[tuple[int, int]]
#: EG3D FFHQ conventions, the defaults of Triplane and look_at_camera
#: (lp3d.render.camera and lp3d.render.settings agree).
FFHQ_FOCAL: float
FFHQ_RADIUS: float
FFHQ_PIVOT: tuple[float, float, float]
DEFAULT_BOX_WARP: float
DEFAULT_RAY_START: float
DEFAULT_RAY_END: float
FORMAT_VERSION: int
#: lp3d-view's usage text: its flags, defined once in the viewer crate.
VIEW_USAGE: str
#: The triplane file's caps (docs/triplane-format.md, "Caps"), by name.
FILE_LIMITS: dict[str, int]
__version__: str

class Triplane:
    """An EG3D-format triplane: planes (3, 32, H, W), effective decoder weights, scene bounds."""

    def __init__(
        self,
        planes: npt.NDArray[np.float16] | npt.NDArray[np.float32],
        w0: npt.NDArray[np.floating],
        b0: npt.NDArray[np.floating],
        w1: npt.NDArray[np.floating],
        b1: npt.NDArray[np.floating],
        box_warp: float = 1.0,
        ray_start: float = 2.25,
        ray_end: float = 3.3,
        *,
        camera: npt.NDArray[np.floating] | None = None,
        source: str | None = None,
        occupancy: npt.NDArray[np.float32] | None = None,
        occupancy_checksum: int | None = None,
    ) -> None: ...
    @staticmethod
    def load(path: str | PathLike[str]) -> Triplane: ...
    def save(self, path: str | PathLike[str]) -> None: ...
    @property
    def planes(self) -> npt.NDArray[np.float16] | npt.NDArray[np.float32]: ...
    @property
    def w0(self) -> npt.NDArray[np.float32]: ...
    @property
    def b0(self) -> npt.NDArray[np.float32]: ...
    @property
    def w1(self) -> npt.NDArray[np.float32]: ...
    @property
    def b1(self) -> npt.NDArray[np.float32]: ...
    @property
    def box_warp(self) -> float: ...
    @property
    def ray_start(self) -> float: ...
    @property
    def ray_end(self) -> float: ...
    @property
    def camera(self) -> npt.NDArray[np.float32] | None: ...
    @property
    def source(self) -> str | None: ...
    @property
    def occupancy(self) -> npt.NDArray[np.float32] | None: ...
    def bake_occupancy(self, resolution: int = 64) -> npt.NDArray[np.float32]: ...
    @property
    def device_bytes(self) -> int: ...

def render(
    triplane: Triplane,
    camera: npt.NDArray[np.floating],
    resolution: int = 128,
    depth_resolution: int = 48,
    depth_resolution_importance: int = 48,
    deterministic: bool = True,
    seed: int | None = None,
    outputs: Iterable[str] | None = None,
    white_back: bool = False,
    *,
    transmittance_threshold: float = 0.0,
    empty_threshold: float = 0.0,
    occupancy_epsilon: float = 0.0,
    occupancy_coarse: bool = False,
    baked_subdivisions: int = 0,
    baked_fine_subdivisions: int = 0,
    superres: SuperRes | None = None,
) -> dict[str, npt.NDArray[np.float32]]: ...

class BakedField:
    @property
    def subdivisions(self) -> int: ...
    @property
    def fine_subdivisions(self) -> int: ...
    @property
    def occupancy_epsilon(self) -> float: ...
    @property
    def max_delta(self) -> float: ...
    @property
    def cells(self) -> int: ...
    @property
    def bricks(self) -> int: ...
    @property
    def fine_bricks(self) -> int: ...
    @property
    def bake_seconds(self) -> float: ...
    @property
    def device_bytes(self) -> int: ...
    @property
    def index(self) -> npt.NDArray[np.int64]: ...
    @property
    def values(self) -> npt.NDArray[np.float16]: ...
    @property
    def fine_values(self) -> npt.NDArray[np.float16]: ...

class SuperRes:
    """A folded super-resolution network on the GPU (FoldedSuperResolution's weights, one array per
    ×2 block each): features (B, C, R, R) -> images (B, 3, R * 2**blocks, R * 2**blocks)."""

    def __init__(
        self,
        convs_up: Sequence[npt.NDArray[np.floating[Any]]],
        biases_up: Sequence[npt.NDArray[np.floating[Any]]],
        convs: Sequence[npt.NDArray[np.floating[Any]]],
        biases: Sequence[npt.NDArray[np.floating[Any]]],
        rgb_weights: Sequence[npt.NDArray[np.floating[Any]]],
        rgb_biases: Sequence[npt.NDArray[np.floating[Any]]],
        *,
        input_resolution: int,
    ) -> None: ...
    @staticmethod
    def load(path: str | PathLike[str]) -> SuperRes: ...
    @property
    def in_channels(self) -> int: ...
    @property
    def input_resolution(self) -> int: ...
    @property
    def output_resolution(self) -> int: ...
    def apply(self, features: npt.NDArray[np.floating[Any]]) -> npt.NDArray[np.float32]: ...
    def plan(self) -> dict[str, Any]: ...

def bake(
    triplane: Triplane,
    subdivisions: int = 4,
    occupancy_epsilon: float = 0.0001,
    depth_resolution: int = 48,
    deterministic: bool = True,
    progress: Callable[[int, int], object] | None = None,
    fine_subdivisions: int = 0,
) -> BakedField: ...
def attach_baked(
    triplane: Triplane,
    index: npt.NDArray[np.int64],
    values: npt.NDArray[np.uint16],
    *,
    subdivisions: int,
    occupancy_epsilon: float,
    max_delta: float,
    fine_subdivisions: int = 0,
    fine_values: npt.NDArray[np.uint16] | None = None,
) -> BakedField: ...
def adapter_info() -> dict[str, str]: ...
def last_frame_device_bytes() -> int: ...
def look_at_camera(
    *,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    radius: float = 2.7,
    lookat: tuple[float, float, float] = (0.0, 0.0, 0.2),
    focal: float = 4.2647,
) -> npt.NDArray[np.float32]: ...

# The renderer's WGSL stage files, name -> source, in the order it joins them into one module.
def shader_sources() -> dict[str, str]: ...
def view(
    path: str | PathLike[str] | None = None,
    *,
    screenshot: str | PathLike[str] | None = None,
    yaw: float = 0.0,
    pitch: float = 0.0,
    resolution: int = 128,
    depth_resolution: int = 48,
    depth_resolution_importance: int = 48,
    frame_budget_ms: float = 100.0,
    frames: int = 3,
    drag_frames: int = 0,
    bake: bool = True,
    fine_field: bool = True,
    superres: str | PathLike[str] | None = None,
    no_superres: bool = False,
) -> None: ...
def view_options(argv: list[str]) -> dict[str, Any]: ...
