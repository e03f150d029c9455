"""One self-contained web page of a triplane, rendered in the browser by lp3d's own WGSL on WebGPU.

The page (``page.html`` with ``gpu.js`` and ``viewer.js``, this package's data files, as one script)
holds, in one JSON block:

* the planes, channel-last ``(3, H, W, 32)`` little-endian, in the file's precision (float32 becomes
  float16 on request), base64: the layout the renderer uploads
  (``crates/renderer/src/renderer/upload.rs``), float16 as packed pairs;
* the decoder's effective weights as the renderer's ``Decoder`` uniform (``gpu_types.rs``), float32;
* the scene bounds, the camera conventions (:mod:`lp3d.render.camera`'s FFHQ focal, radius and pivot)
  and the render settings (:class:`~lp3d.render.settings.RenderSettings`);
* the renderer's WGSL stage files as the renderer compiles them (``lp3d_render.shader_sources()``,
  ``include_str!``-ed from ``crates/renderer/shaders/`` into the extension), in module order;
* optionally a super-resolution network as the renderer lays it out (``lp3d_render.SuperRes.plan``:
  the packed weights, base64, and the dispatches in order), which super-resolves the still view.

Nothing is fetched when the page is viewed (its Content-Security-Policy forbids it), and no text from
the file is run as code: the data is JSON in a ``<script type="application/json">`` block (``<``,
``>`` and ``&`` escaped), parsed with ``JSON.parse`` and shown with ``textContent``; the one script
is this package's ``gpu.js`` + ``viewer.js``, allowed by its hash. Test mode: ``#probe=YAW,PITCH`` (see
``docs/share.md``) logs the RGB image of that view at :data:`PROBE_SETTINGS` as one console line.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import os
import re
from importlib import resources
from typing import Any

import numpy as np

from lp3d.atomic import atomic_path
from lp3d.errors import safe_text
from lp3d.render.camera import FFHQ_FOCAL, FFHQ_PIVOT, FFHQ_RADIUS
from lp3d.render.native import renderer
from lp3d.render.settings import HIDDEN, N_CHANNELS, N_OUT, RenderSettings
from lp3d.render.triplane import TriplaneData

__all__ = [
    "PAGE_VERSION",
    "PROBE_PREFIX",
    "PROBE_SETTINGS",
    "assemble_page",
    "build_page",
    "decoder_uniform",
    "page_data",
    "plane_dtype",
    "plane_texels",
    "shader_stages",
    "superres_data",
    "view_data",
    "viewer_scripts",
    "write_page",
]

#: Version of the page's data block (``viewer.js`` refuses any other).
PAGE_VERSION = 1
#: The console line prefix of the test mode's image.
PROBE_PREFIX = "LP3D_PROBE "
#: What the test mode renders: 64², 48+48 samples, exact EG3D semantics (deterministic, no skips).
PROBE_SETTINGS = RenderSettings(resolution=64, depth_resolution=48, depth_resolution_importance=48)
#: Float16's largest finite value: float32 planes beyond it cannot be stored as float16.
FLOAT16_MAX = float(np.finfo(np.float16).max)
#: The scripts of every page that renders a triplane: these files of this package, in this order.
VIEWER_SCRIPTS = ("gpu.js", "viewer.js")
#: The share page's own script (its entry point), after :data:`VIEWER_SCRIPTS`.
SHARE_SCRIPT = "share.js"
#: The entry points the page builds pipelines for (all three of the renderer's module).
ENTRY_POINTS = ("render_rays", "depth_bounds_pass", "present")


def _package_text(name: str) -> str:
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def shader_stages() -> list[tuple[str, str]]:
    """``[(file, WGSL source)]``: the renderer's stage files in the order it joins them into its one
    module (``lp3d_render.shader_sources()``; ``tests/view/test_share.py`` checks them against
    ``crates/renderer/shaders/``)."""
    stages = list(renderer().shader_sources().items())
    module = "\n".join(source for _, source in stages)
    for entry in ENTRY_POINTS:
        if f"fn {entry}(" not in module:
            raise RuntimeError(f"the renderer's WGSL has no entry point {entry}; lp3d_render is out of date")
    return stages


def plane_dtype(tri: TriplaneData, *, float16: bool = False) -> str:
    """``"float16"`` or ``"float32"``: the planes' dtype in the page, the file's unless ``float16``
    asks to round float32 planes (half the size; the images then differ from the file's, see
    ``docs/share.md``)."""
    return "float16" if float16 or tri.planes.dtype == np.float16 else "float32"


def plane_texels(tri: TriplaneData, *, float16: bool = False) -> bytes:
    """The planes as the renderer uploads them: channel-last (3, H, W, 32), little-endian, float16 (the
    renderer packs channels 2i and 2i + 1 of a texel into one u32, low half first: these bytes) or
    float32, as :func:`plane_dtype` says. Float32 values beyond float16's range refuse ``float16``."""
    planes = tri.planes
    half = plane_dtype(tri, float16=float16) == "float16"
    if half and planes.dtype != np.float16:
        peak = float(np.abs(planes).max())
        if peak > FLOAT16_MAX:
            raise ValueError(
                f"planes: values up to {peak:.4g} exceed float16's range ({FLOAT16_MAX:g}); "
                "share them as float32 (without --float16)"
            )
    return np.ascontiguousarray(planes.transpose(0, 2, 3, 1), dtype="<f2" if half else "<f4").tobytes()


def decoder_uniform(tri: TriplaneData) -> bytes:
    """The renderer's ``Decoder`` uniform (``shaders/params.wgsl``): w0 (64, 32), b0 (64), w1 (33, 64),
    b1 (33, padded to 36), float32 little-endian, row-major."""
    b1 = np.zeros(-(-N_OUT // 4) * 4, np.float32)
    b1[:N_OUT] = tri.b1
    parts = [tri.w0.reshape(HIDDEN * N_CHANNELS), tri.b0, tri.w1.reshape(N_OUT * HIDDEN), b1]
    return np.concatenate([np.asarray(p, dtype="<f4") for p in parts]).tobytes()


def view_data(
    tri: TriplaneData,
    *,
    settings: RenderSettings | None = None,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    probe: RenderSettings = PROBE_SETTINGS,
    superres: Any | None = None,
) -> dict[str, Any]:
    """What a page needs to render any triplane with ``tri``'s decoder and bounds (JSON-ready): the
    decoder uniform, the bounds, the camera, the settings, the probe and the WGSL. Everything of
    :func:`page_data` but the planes, so that a page whose planes arrive later (``lp3d serve``) shares
    it; ``settings`` is the final quality of the viewer (default :class:`RenderSettings`), which
    renders exact EG3D semantics only, ``probe`` what the test mode renders, ``superres`` (an
    ``lp3d_render.SuperRes`` for ``tri``'s decoder) the network that super-resolves the still view."""
    settings = RenderSettings() if settings is None else settings
    for s, what in ((settings, "the shared page"), (probe, "the page's probe")):
        s.validate()
        s.require_exact(what)
        if not s.deterministic:
            raise ValueError(f"{what} renders deterministically (deterministic=True)")
    if not -90.0 < pitch_deg < 90.0:
        raise ValueError(f"pitch_deg must be in (-90, 90), got {pitch_deg!r}")
    decoder = decoder_uniform(tri)
    return {
        "decoder": {"uniform_bytes": len(decoder), "base64": base64.b64encode(decoder).decode("ascii")},
        "bounds": {"box_warp": tri.box_warp, "ray_start": tri.ray_start, "ray_end": tri.ray_end},
        "camera": {
            "focal": FFHQ_FOCAL,
            "radius": FFHQ_RADIUS,
            "lookat": list(FFHQ_PIVOT),
            "yaw": float(yaw_deg),
            "pitch": float(pitch_deg),
        },
        "settings": {
            "resolution": settings.resolution,
            "depth_resolution": settings.depth_resolution,
            "depth_resolution_importance": settings.depth_resolution_importance,
            "white_back": settings.white_back,
        },
        "probe": {
            "resolution": probe.resolution,
            "depth_resolution": probe.depth_resolution,
            "depth_resolution_importance": probe.depth_resolution_importance,
            "prefix": PROBE_PREFIX,
        },
        "shaders": [list(stage) for stage in shader_stages()],
        "superres": None if superres is None else superres_data(superres),
    }


def superres_data(sr: Any) -> dict[str, Any]:
    """An ``lp3d_render.SuperRes`` as the page runs it (``gpu.js``, ``buildSuperres``): the renderer's
    plan of it, with its packed float32 weights base64."""
    plan = sr.plan()
    weights = np.ascontiguousarray(plan.pop("weights"), dtype="<f4")
    return {
        **plan,
        "weights_floats": int(weights.size),
        "weights_base64": base64.b64encode(weights).decode("ascii"),
    }


def page_data(
    tri: TriplaneData,
    *,
    title: str,
    settings: RenderSettings | None = None,
    float16: bool = False,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    superres: Any | None = None,
) -> dict[str, Any]:
    """The page's data block (JSON-ready) for a validated triplane; ``settings`` is the final quality
    of the viewer (default :class:`RenderSettings`), which renders exact EG3D semantics only;
    ``superres`` as :func:`view_data`."""
    view = view_data(tri, settings=settings, yaw_deg=yaw_deg, pitch_deg=pitch_deg, superres=superres)
    tri.validate()
    h, w = tri.plane_size
    return {
        "format": "lp3d-share",
        "version": PAGE_VERSION,
        "title": safe_text(title),
        "source": None if tri.source is None else safe_text(tri.source),
        "planes": {
            "height": h,
            "width": w,
            "dtype": plane_dtype(tri, float16=float16),
            "layout": "(3, H, W, 32) channel-last, little-endian",
            "base64": base64.b64encode(plane_texels(tri, float16=float16)).decode("ascii"),
        },
        **view,
    }


def _json_for_html(data: dict[str, Any]) -> str:
    """JSON that cannot end its ``<script>`` block or open a comment: ``<``, ``>`` and ``&`` (only
    ever inside strings) become ``\\u003c``, ``\\u003e``, ``\\u0026``; non-ASCII is escaped too."""
    text = json.dumps(data, ensure_ascii=True, allow_nan=False, separators=(",", ":"))
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def viewer_scripts() -> list[str]:
    """The texts of the scripts every page that renders a triplane runs first (``gpu.js``, the
    renderer on WebGPU, and ``viewer.js``, the viewer and the test mode), in order."""
    return [_package_text(name) for name in VIEWER_SCRIPTS]


def assemble_page(template: str, scripts: list[str], data: dict[str, Any], values: dict[str, str]) -> str:
    """An HTML page from ``template``: ``{{SCRIPT}}`` becomes the ``scripts`` joined (one inline
    script, allowed by its hash: ``{{SCRIPT_HASH}}``), ``{{DATA}}`` the JSON of ``data`` made safe for a
    ``<script type="application/json">`` block, and ``{{NAME}}`` each of ``values`` (already escaped
    by the caller). The share page and ``lp3d serve``'s page are both built by it."""
    script = "\n".join(scripts)
    if re.search(r"</script|<!--", script, re.IGNORECASE):
        raise RuntimeError("a page's scripts must not contain '</script' or '<!--'")
    digest = base64.b64encode(hashlib.sha256(script.encode("utf-8")).digest()).decode("ascii")
    filled = {**values, "SCRIPT_HASH": f"sha256-{digest}", "DATA": _json_for_html(data), "SCRIPT": script}
    # One pass: inserted text is never scanned for markers again.
    return re.sub(r"\{\{([A-Z_]+)\}\}", lambda m: filled[m.group(1)], template)


def build_page(
    tri: TriplaneData,
    *,
    title: str = "lp3d head",
    settings: RenderSettings | None = None,
    float16: bool = False,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    superres: Any | None = None,
) -> str:
    """The page's HTML (see the module docstring); arguments as :func:`page_data`."""
    from lp3d import __version__

    data = page_data(
        tri,
        title=title,
        settings=settings,
        float16=float16,
        yaw_deg=yaw_deg,
        pitch_deg=pitch_deg,
        superres=superres,
    )
    scripts = [*viewer_scripts(), _package_text(SHARE_SCRIPT)]
    values = {"TITLE": html.escape(safe_text(title)), "VERSION": html.escape(__version__)}
    return assemble_page(_package_text("page.html"), scripts, data, values)


def write_page(path: str | os.PathLike[str], tri: TriplaneData, **kwargs: Any) -> int:
    """Write :func:`build_page` of ``tri`` to ``path`` atomically (a temporary file renamed into place:
    an existing file is replaced only by a complete page); returns its size in bytes."""
    text = build_page(tri, **kwargs).encode("utf-8")
    with atomic_path(path, parents=False) as tmp, open(tmp, "wb") as f:
        f.write(text)
    return len(text)
