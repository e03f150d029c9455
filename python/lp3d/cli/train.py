"""``lp3d train``: distil a teacher into the triplane encoder.

The options are ``python -m lp3d.train``'s, defined once in
:func:`lp3d.training.cli.add_arguments`; that module needs torch (the ``train`` extra), so it is
imported only when this subcommand is parsed or run."""

from __future__ import annotations

from lp3d.cli.common import module_command

HELP = "distil a teacher into the encoder (python -m lp3d.train; needs torch)"
#: This subcommand's options import torch: the top-level parser adds them only when it is named.
LAZY = True

add_arguments, run = module_command("lp3d.training.cli")
