"""``python -m hmflow.cli``: the command line, as the ``hmflow`` script runs it."""

import sys

from hmflow.cli import app

if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
