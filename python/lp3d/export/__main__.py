"""``python -m lp3d.export``: the command line of :mod:`lp3d.export`."""

import sys

from lp3d.export.package import main

sys.exit(main())
