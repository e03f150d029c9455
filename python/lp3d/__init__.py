"""lp3d: single-image portrait to EG3D triplane, rendered in real time.

The package follows the data flow (``docs/architecture.md``): :mod:`lp3d.photo` (photos in),
:mod:`lp3d.nets` (the networks), :mod:`lp3d.lift` (a model package lifts a photo to a triplane),
:mod:`lp3d.render` (cameras, settings, the triplane and its file, the reference and torch renderers),
:mod:`lp3d.teachers`, :mod:`lp3d.training` and :mod:`lp3d.cli`, with the plumbing modules
:mod:`lp3d.errors`, :mod:`lp3d.atomic`, :mod:`lp3d.array_cache`, :mod:`lp3d.images` and
:mod:`lp3d.outputs`. Subpackages are imported on demand, so ``import lp3d`` stays cheap and never
pulls in torch or the native renderer.
"""

__version__ = "0.1.0"
