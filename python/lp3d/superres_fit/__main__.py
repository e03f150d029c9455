"""``python -m lp3d.superres_fit``: the command line of :mod:`lp3d.superres_fit`."""

import sys

from lp3d.superres_fit.fit import main

sys.exit(main())
