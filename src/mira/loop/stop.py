"""Stopping a run on SIGINT (Ctrl-C) or SIGTERM without losing its work.

While the trainer runs, either signal only *asks* it to stop: it finishes the step in progress (an
evaluation or an outer-loop cycle in progress completes first), truncates the episode it is in, takes a
checkpoint there, writes ``policy.pt`` and raises :class:`~mira.errors.Interrupted`, which the command
line records as status ``interrupted`` (exit status 130 for SIGINT, 143 for SIGTERM). A second signal
stops at once, without that checkpoint (the previous one still resumes the run), unless it comes within
:data:`SAME_REQUEST_S` of the first: then it is the same request arriving twice (``pkill -f mira`` signals
both a sweep and its runs, and the sweep forwards its own to each run), and the checkpoint is still taken.

Outside the trainer (setting a run up) SIGTERM is made to interrupt like Ctrl-C: :func:`sigterm_interrupts`.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from collections.abc import Iterator
from types import FrameType
from typing import Any

from mira.errors import Interrupted

log = logging.getLogger(__name__)

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
SAME_REQUEST_S = 1.0
"""A second signal this soon after the first asks for the same stop, not for a stop without the checkpoint."""


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


class StopRequest:
    """Turns SIGINT and SIGTERM into a request (:attr:`signum`) the trainer reads between steps, while
    entered (in the main thread only: elsewhere signals cannot be handled, and nothing changes)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._first_at = 0.0
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopRequest:
        if _main_thread():
            for sig in _SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        if self.signum is not None:
            if time.monotonic() - self._first_at < SAME_REQUEST_S:
                log.warning("%s: already stopping with a checkpoint", signal.Signals(signum).name)
                return
            raise Interrupted(signum)  # asked twice: stop now, without the checkpoint
        self.signum, self._first_at = signum, time.monotonic()
        log.warning("%s: stopping after this step with a checkpoint (send it again to stop at once)",
                    signal.Signals(signum).name)


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises :class:`~mira.errors.Interrupted` as Ctrl-C raises ``KeyboardInterrupt`` (main
    thread only), so that ``kill PID`` is recorded like Ctrl-C rather than killing the process mid-write."""
    if not _main_thread():
        yield
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        raise Interrupted(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
