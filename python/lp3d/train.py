"""``python -m lp3d.train``: distil a teacher into the LP3D encoder (``lp3d train`` is the same command).

The command line is :mod:`lp3d.cli.train`; the library it calls is :func:`lp3d.training.train` (the
package's docstring describes the recipe). This module is only the README's command: import the
training names from :mod:`lp3d.training`.
"""

from __future__ import annotations

from lp3d.cli.train import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
