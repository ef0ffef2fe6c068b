"""``python -m bayesmag ...``: the command line (the same as the ``bayesmag`` console script)."""

import sys

from bayesmag._src.app.cli import main

if __name__ == "__main__":
    sys.exit(main())
