"""Fail points: named places where the fault-injection suite can kill the process on purpose.

Inert unless the environment variable ``MIRA_FAILPOINTS`` is set, e.g.
``MIRA_FAILPOINTS="checkpoint.after_payload:2"`` kills the process with SIGKILL the 2nd time that
point is reached. This is how the test suite proves that a kill *between* the two writes of a
checkpoint, in the middle of a program update or around an SRR call loses nothing (the same idea as
the fail points of storage engines). Reading one environment variable once costs nothing in the
hot path: the points sit on checkpoint and outer-loop paths only.
"""

from __future__ import annotations

import os
import signal
from collections import Counter

_SPEC = os.environ.get("MIRA_FAILPOINTS", "")
_TARGETS: dict[str, int] = {}
for item in filter(None, (p.strip() for p in _SPEC.split(","))):
    name, _, count = item.partition(":")
    _TARGETS[name] = int(count or 1)
_SEEN: Counter[str] = Counter()


def failpoint(name: str) -> None:
    """Kill this process with SIGKILL if ``name`` is armed and reached for the armed time."""
    if not _TARGETS or name not in _TARGETS:
        return
    _SEEN[name] += 1
    if _SEEN[name] == _TARGETS[name]:
        os.kill(os.getpid(), signal.SIGKILL)
