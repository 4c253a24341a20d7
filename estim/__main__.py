"""``python -m estim``: the command line (see ``estim.app._cli``)."""

import sys

from .app._cli import main

if __name__ == "__main__":
    sys.exit(main())
