"""``python -m mira``: the ``mira`` command, for environments where its console script is not on PATH."""

import os
import sys

from mira.cli import main

os.environ.setdefault("PYTHONUNBUFFERED", "1")
sys.exit(main())
