"""``python -m bayesmag ...``: the same as the ``bayesmag`` command."""

import sys

from bayesmag._src.app.cli import main

sys.exit(main())
