"""``python -m bayesmag ...``: the same as the ``bayesmag`` command."""

import sys

from bayesmag._src.cli import main

sys.exit(main())
