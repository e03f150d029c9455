"""Sharing a lifted head as one web page: :mod:`~lp3d.share.page` builds a self-contained HTML file
that renders a triplane in the browser with lp3d's own WGSL kernels on WebGPU (``lp3d share``;
``docs/share.md``). Its data files: ``page.html`` (the page), ``gpu.js`` (the renderer's pipelines
and dispatches on WebGPU) and ``viewer.js`` (the viewer and the test mode), which ``lp3d serve``'s
page runs too, and ``share.js`` (this page's entry point), one script in the page.

May import: :mod:`lp3d.render` (the triplane, settings, camera conventions, and the WGSL through
``lp3d_render``) and the plumbing modules (:mod:`lp3d.atomic`, :mod:`lp3d.errors`). Not the command
line.
"""

from lp3d.share.page import (
    PAGE_VERSION,
    PROBE_PREFIX,
    PROBE_SETTINGS,
    assemble_page,
    build_page,
    decoder_uniform,
    page_data,
    plane_dtype,
    plane_texels,
    shader_stages,
    view_data,
    viewer_scripts,
    write_page,
)

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
    "view_data",
    "viewer_scripts",
    "write_page",
]
