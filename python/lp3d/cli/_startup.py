"""Imported first by :mod:`lp3d.cli`, before the slow imports (numpy, the renderer, torch): Ctrl-C from
here until a command runs ends the ``lp3d`` process with one line and status 130, no traceback
(:func:`lp3d.errors.quiet_startup_interrupts`; a program that imports :mod:`lp3d.cli` is not
affected)."""

from lp3d.errors import quiet_startup_interrupts

quiet_startup_interrupts()
