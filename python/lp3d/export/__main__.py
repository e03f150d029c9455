"""``python -m lp3d.export``: the same command as ``lp3d export``."""

import sys

from lp3d.export.package import main

sys.exit(main())
