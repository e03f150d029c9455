"""The networks (torch): :mod:`~lp3d.nets.encoder` (the LP3D encoder; its sizes and ``CONFIGS`` in
:mod:`~lp3d.nets.encoder_config`, its parts in :mod:`~lp3d.nets.encoder_blocks`,
:mod:`~lp3d.nets.encoder_stages` and :mod:`~lp3d.nets.plane_basis`),
:mod:`~lp3d.nets.superres` (EG3D's super-resolution, ``SUPERRES_CONFIGS``),
:mod:`~lp3d.nets.discriminator` (EG3D's dual discriminator, ``DISCRIMINATOR_CONFIGS``) and
:mod:`~lp3d.nets.stylegan_ops` (the StyleGAN2 layers they share).

May import: torch only. Nothing here knows about renderers, teachers,
training or files on disk.
"""
