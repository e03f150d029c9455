"""lp3d_render: the lp3d triplane renderer (Rust, wgpu, WGSL compute shaders).

Renders EG3D-format triplanes exactly as EG3D does (deterministic by default)::

    import lp3d_render
    tri = lp3d_render.Triplane.load("head.npz")
    out = lp3d_render.render(tri, camera, resolution=128)   # camera: (25,) or (B, 25)
    out["rgb"]      # (3, R, R) float32 in about [-1, 1]
    out["depth"]    # (R, R)

See ``docs/triplane-format.md`` for the file format and ``lp3d.render.camera`` for cameras.
"""

from lp3d_render._guard import (  # fork and size checks
    adapter_info,
    attach_baked,
    bake,
    last_frame_device_bytes,
    render,
    view,
)
from lp3d_render._lp3d_render import (
    DEFAULT_BOX_WARP,
    DEFAULT_RAY_END,
    DEFAULT_RAY_START,
    FFHQ_FOCAL,
    FFHQ_PIVOT,
    FFHQ_RADIUS,
    FILE_LIMITS,
    FORMAT_VERSION,
    MAX_RESOLUTION,
    MAX_SAMPLES,
    PLANE_AXES,
    VIEW_USAGE,
    BakedField,
    SuperRes,
    Triplane,
    __version__,
    look_at_camera,
    shader_sources,
    view_options,
)

__all__ = [
    "BakedField",
    "DEFAULT_BOX_WARP",
    "DEFAULT_RAY_END",
    "DEFAULT_RAY_START",
    "FFHQ_FOCAL",
    "FFHQ_PIVOT",
    "FFHQ_RADIUS",
    "FILE_LIMITS",
    "FORMAT_VERSION",
    "MAX_RESOLUTION",
    "MAX_SAMPLES",
    "PLANE_AXES",
    "SuperRes",
    "Triplane",
    "VIEW_USAGE",
    "__version__",
    "adapter_info",
    "attach_baked",
    "bake",
    "last_frame_device_bytes",
    "look_at_camera",
    "render",
    "shader_sources",
    "view",
    "view_options",
]
