"""``mira.loop.stop``: a stop signal is a request the trainer answers with a checkpoint; a second signal
stops at once, unless it is the same request arriving twice (a sweep and ``pkill`` both signalling)."""

from __future__ import annotations

import signal

import pytest

from mira.errors import Interrupted
from mira.loop import stop as stop_module
from mira.loop.stop import StopRequest


def test_a_signal_repeated_at_once_is_one_request_and_a_later_one_stops_at_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    with StopRequest() as stop:
        signal.raise_signal(signal.SIGTERM)
        signal.raise_signal(signal.SIGINT)  # the same stop, sent by a second sender
        assert stop.signum == signal.SIGTERM
        monkeypatch.setattr(stop_module, "SAME_REQUEST_S", 0.0)  # as if the second came later
        with pytest.raises(Interrupted) as raised:
            signal.raise_signal(signal.SIGINT)
        assert raised.value.signum == signal.SIGINT
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers restored on exit
