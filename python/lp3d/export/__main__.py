"""``python -m lp3d.export``: the same command as ``lp3d export`` (:mod:`lp3d.cli.export`)."""

import sys

from lp3d.cli.export import main

sys.exit(main())
