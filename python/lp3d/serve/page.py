"""``lp3d serve``'s page: ``serve.html`` with one script, ``lp3d share``'s renderer and viewer
(:func:`lp3d.share.viewer_scripts`) followed by this package's ``serve.js``, and a data block holding
everything to render the model's triplanes (:func:`lp3d.share.view_data`: the decoder, bounds, camera
conventions, settings and the renderer's WGSL) but the planes, which come from the server per photo
or webcam frame. Built once when the server starts; it names no server address, so it works on any
host and port. Test mode: ``#probe=YAW,PITCH`` logs, for the first photo and the first live frame,
one console line ``LP3D_SERVE_PROBE {json}`` with the view rendered at :data:`SERVE_PROBE_SETTINGS`
and the planes it drew (``tests/cli/test_serve.py``).
"""

from __future__ import annotations

import base64
import hashlib
import html
from importlib import resources
from typing import Any

import numpy as np

from lp3d.lift.loaded import LoadedEncoder
from lp3d.render.settings import RenderSettings
from lp3d.serve.lifting import MAX_FRAME_BYTES, MAX_FRAME_PIXELS, PHOTO_LIMITS
from lp3d.share import assemble_page, view_data, viewer_scripts

__all__ = ["PAGE_FORMAT", "PAGE_POLICY", "SERVE_PROBE_SETTINGS", "build_serve_page", "live_settings"]

#: The data block's format name and version (``serve.js`` refuses others).
PAGE_FORMAT = ("lp3d-serve", 1)
#: What the test mode renders: small (WebGPU on a CPU takes seconds per 32² frame), exact semantics.
SERVE_PROBE_SETTINGS = RenderSettings(resolution=32, depth_resolution=24, depth_resolution_importance=24)
#: The page's content-security policy (also its header, with ``frame-ancestors``): ``lp3d share``'s,
#: with connections to this server only (the API and the WebSocket) and the webcam's stream.
PAGE_POLICY = (
    "default-src 'none'; script-src '{script_hash}'; style-src 'unsafe-inline'; connect-src 'self'; "
    "media-src mediastream: blob:"
)


def live_settings() -> dict[str, Any]:
    """How the page captures webcam frames: size, rate, JPEG quality, frames in flight."""
    return {"width": 320, "height": 240, "max_fps": 30, "jpeg_quality": 0.8, "in_flight": 2}


def build_serve_page(
    encoder: LoadedEncoder, *, settings: RenderSettings | None = None, token_required: bool = False
) -> tuple[str, str]:
    """``(html, script hash)`` of the page for ``encoder``'s model; ``settings`` is the viewer's final
    quality (default :class:`RenderSettings`)."""
    from lp3d import __version__
    from lp3d.lift.gpu_superres import superres_on_gpu

    pkg = encoder.package
    superres = None if pkg.superres is None else superres_on_gpu(pkg.superres)
    t = pkg.triplane_resolution
    blank = pkg.triplane(np.zeros((3, 32, t, t), np.float32))
    data = {
        "format": PAGE_FORMAT[0],
        "version": PAGE_FORMAT[1],
        "model": encoder.description,
        "image_size": pkg.image_size,
        "token_required": token_required,
        "limits": {**PHOTO_LIMITS, "max_frame_bytes": MAX_FRAME_BYTES, "max_frame_pixels": MAX_FRAME_PIXELS},
        "live": live_settings(),
        **view_data(blank, settings=settings, probe=SERVE_PROBE_SETTINGS, superres=superres),
    }
    scripts = [*viewer_scripts(), resources.files(__package__).joinpath("serve.js").read_text("utf-8")]
    template = resources.files(__package__).joinpath("serve.html").read_text("utf-8")
    digest = hashlib.sha256("\n".join(scripts).encode("utf-8")).digest()
    script_hash = "sha256-" + base64.b64encode(digest).decode("ascii")
    values = {
        "VERSION": html.escape(__version__),
        "POLICY": html.escape(PAGE_POLICY.format(script_hash=script_hash)),
    }
    return assemble_page(template, scripts, data, values), script_hash
