"""``python -m abmpm`` is the ``abmpm`` command."""

import sys

from abmpm.cli import main

if __name__ == "__main__":
    sys.exit(main())
