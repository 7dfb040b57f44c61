"""``python -m statmc``: the command line, the same as the ``statmc`` console script."""

import sys

from .cli import main

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
