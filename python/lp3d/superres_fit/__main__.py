"""``python -m lp3d.superres_fit``: the same command as ``lp3d superres-fit``."""

import sys

from lp3d.cli.superres_fit import main

sys.exit(main())
