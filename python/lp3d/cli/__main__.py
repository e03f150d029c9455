"""``python -m lp3d.cli`` is ``lp3d``."""

import sys

from lp3d.cli import main

sys.exit(main())
