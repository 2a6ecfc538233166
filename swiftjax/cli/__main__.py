"""``python -m swiftjax.cli``: the ``swiftjax`` command."""

import sys

from swiftjax.cli import main

if __name__ == "__main__":
    sys.exit(main())
