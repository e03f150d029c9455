"""Lifting a photo with a trained model: :mod:`~lp3d.lift.model_package` (the ``MODEL.onnx`` +
``MODEL.json`` package, spec in ``docs/model-package.md``) and :mod:`~lp3d.lift.inference` (runs the
encoder with ONNX Runtime or torch and returns a :class:`~lp3d.render.triplane.TriplaneData`).
The package's pieces: :mod:`~lp3d.lift.sidecar` (the ``MODEL.json`` format and its checks),
:mod:`~lp3d.lift.loaded` (what loading hands back), :mod:`~lp3d.lift.onnx_backend` and
:mod:`~lp3d.lift.torch_backend` (one loader per backend). After the encoder:
:mod:`~lp3d.lift.refine` fits its triplane to the photo (``lp3d encode --refine``; needs torch) and
:mod:`~lp3d.lift.steady` averages a video's triplanes over neighbouring frames (``lp3d video --steady``).

May import: :mod:`lp3d.render`, :mod:`lp3d.nets` (only for the torch path), the plumbing modules
(:mod:`lp3d.atomic`, :mod:`lp3d.errors`). Not training, not the command line.
"""
