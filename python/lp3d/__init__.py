"""lp3d: single-image portrait to EG3D triplane, rendered in real time.

Submodules are imported on demand (``lp3d.camera``, ``lp3d.triplane``, ``lp3d.triplane_io``,
``lp3d.reference``, ...) so that ``import lp3d`` stays cheap and never pulls in torch or the
native renderer.
"""

__version__ = "0.1.0"
