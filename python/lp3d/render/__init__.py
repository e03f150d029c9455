"""Rendering: the conventions every renderer shares and the two Python renderers.

What is here, along the data flow:

* conventions: :mod:`~lp3d.render.camera` (EG3D's 25-float label, look-at, FFHQ constants, orbits),
  :mod:`~lp3d.render.settings` (:class:`~lp3d.render.settings.RenderSettings`, scene bounds, caps,
  EG3D's numerics), :mod:`~lp3d.render.triplane` (:class:`~lp3d.render.triplane.TriplaneData`,
  ``PLANE_AXES``), :mod:`~lp3d.render.sampling_rng` (the jitter RNG);
* the triplane file: :mod:`~lp3d.render.triplane_io` and :mod:`~lp3d.render.npz_reader` (no pickle);
* renderers: :mod:`~lp3d.render.reference` (float64 NumPy, the ground truth),
  :mod:`~lp3d.render.torch_twin` (differentiable, for training; its stages in
  :mod:`~lp3d.render.torch_stages`), :mod:`~lp3d.render.native` (the
  WGSL renderer ``lp3d_render``, imported lazily);
* things made from a triplane: :mod:`~lp3d.render.baked` (the baked field's float64 reference),
  :mod:`~lp3d.render.mesh` (marching cubes), and :mod:`~lp3d.render.sample_scenes` (hand-built test
  triplanes);
* scoring: :mod:`~lp3d.render.psnr` (the one PSNR of lp3d).

May import: :mod:`lp3d.errors`, :mod:`lp3d.atomic` and ``lp3d_render``. Nothing here imports the
networks, training or the command line. ``torch_twin``, ``torch_stages`` and ``psnr`` need torch;
:func:`~lp3d.render.triplane.mirror_planes` imports it only for tensor planes, and the rest runs on
NumPy alone.
"""
