"""``python -m mira``: the ``mira`` command, for environments where its console script is not on PATH."""

import os
import sys

from mira.cli import main

if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
