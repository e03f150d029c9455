"""``lp3d eval``: evaluate a trained encoder on held-out teacher identities.

The options are defined once, in
:func:`lp3d.evaluation.evaluate.add_arguments`; that module needs torch (the ``train`` extra), so it
is imported only when this subcommand is parsed or run."""

from __future__ import annotations

from lp3d.cli.common import module_command

HELP = "evaluate a trained encoder on held-out identities (needs torch)"
#: This subcommand's options import torch: the top-level parser adds them only when it is named.
LAZY = True

add_arguments, run = module_command("lp3d.evaluation.evaluate")
