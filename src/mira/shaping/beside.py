"""Work that may run beside the agent: one worker thread, or the caller's thread, the same either way.

HARS's training step and a cycle's no-grad shaping pass read only what they are handed, so they can run
on a second core while the agent updates. :class:`Beside` is that seam: :meth:`Beside.start` runs a
function now (inline) or on the worker, and :meth:`Beside.land` returns its result when the caller
needs it; :meth:`Beside.split` hands out a list result as one Future per element. Nothing in the
computation depends on where it ran (``tests/test_shaping_e2e.py`` compares both bit for bit), so the
loss code never knows.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

import torch

T = TypeVar("T")


class Beside(Generic[T]):
    """At most one pending result of type ``T``, computed inline or on one worker thread."""

    def __init__(self, background: bool) -> None:
        self.background = background
        self._pending: Future[T] | tuple[T] | None = None
        self._executor: ThreadPoolExecutor | None = None

    def start(self, fn: Callable[..., T], *args: Any, inline: bool = False) -> None:
        """Run ``fn(*args)``: on the worker when running in the background (and not ``inline``), else now.
        The previous result must have landed."""
        assert self._pending is None, "the previous result has not landed"
        if self.background and not inline:
            self._pending = self._worker().submit(fn, *args)
        else:
            self._pending = (fn(*args),)

    @property
    def pending(self) -> bool:
        """Whether a result has been started and not landed."""
        return self._pending is not None

    def land(self) -> T | None:
        """The pending result (waiting for it if needed), or None when there is none; clears it."""
        pending, self._pending = self._pending, None
        if pending is None:
            return None
        return pending.result() if isinstance(pending, Future) else pending[0]

    def split(self, fn: Callable[..., list[torch.Tensor]], n: int, *args: Any) -> list[Future[torch.Tensor]]:
        """``fn(*args)``, a list of ``n`` tensors, computed on the worker and handed out as one Future per
        element (a failure reaches every one)."""
        job = self._worker().submit(fn, *args)
        parts: list[Future[torch.Tensor]] = [Future() for _ in range(n)]

        def deliver(done: Future[list[torch.Tensor]]) -> None:
            error = done.exception()
            for i, part in enumerate(parts):
                if error is not None:
                    part.set_exception(error)
                else:
                    part.set_result(done.result()[i])

        job.add_done_callback(deliver)
        return parts

    def _worker(self) -> ThreadPoolExecutor:
        if self._executor is None:
            # One worker, one intra-op thread: the work is small ops, and it runs beside the agent.
            self._executor = ThreadPoolExecutor(1, thread_name_prefix="hars-train", initializer=torch.set_num_threads,
                                                initargs=(1,))
            weakref.finalize(self, self._executor.shutdown, wait=False)
        return self._executor

    def close(self) -> None:
        """Shut the worker down (a later use starts a new one)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None
