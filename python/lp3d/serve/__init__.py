"""``lp3d serve``: a local web app that lifts a dropped photo or the webcam's frames with the model
and renders the head live in the browser with the renderer's own WGSL on WebGPU (``docs/serve.md``).

* :mod:`~lp3d.serve.lifting`: images from bytes (the photo loader's checks), aligned, steadied and
  encoded; the binary triplane message the page reads;
* :mod:`~lp3d.serve.page`: the page, ``serve.html`` and ``serve.js`` on top of ``lp3d share``'s
  renderer and viewer scripts;
* :mod:`~lp3d.serve.app`: the Starlette app (page, photo API, access checks),
  :mod:`~lp3d.serve.live` (the webcam WebSocket, latest frame wins) and :mod:`~lp3d.serve.jobs`
  (photos kept in memory, their refinement).

Needs the ``serve`` extra (Starlette, uvicorn, websockets): ``pip install 'lp3d[serve]'``.

May import: :mod:`lp3d.share`, :mod:`lp3d.lift`, :mod:`lp3d.photo`, :mod:`lp3d.render` and the
plumbing modules. Not the command line.
"""

from lp3d.serve.server import Server, make_state, missing_extra

__all__ = ["Server", "make_state", "missing_extra"]
