"""Asking a reward engineer until its answer is usable: each reply judged, a refused one sent back.

A model's slips (an unknown feature, a missing ``type``, a division nothing guards) are precise and
usually fixed once the model is shown them, so a refused reply is not the end of the exchange: the
errors and the offending lines go back as a follow-up turn of the same conversation, at most
``followups`` times. Every attempt reaches the audit log with its verdict. Only when the last attempt
is refused does the caller fall back, and says so.

The offline rule-based engineer answers from the request's structured context and never reads a
follow-up, so it gets none: a second call could only repeat its first answer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from importlib import resources
from string import Template
from typing import Any, Generic, TypeVar

from mira.engineer.offline import OfflineEngineer
from mira.llm.base import LLMBackend, LLMReply, LLMRequest

T = TypeVar("T")

MAX_FEEDBACK_LINES = 40
"""Errors listed in one follow-up turn; a reply with more is mostly wrong and gets the first ones."""


@dataclass
class Verdict(Generic[T]):
    """What the caller made of one reply: the usable value, or the errors that stop it."""

    value: T | None
    errors: list[str] = field(default_factory=list)
    record: dict[str, Any] = field(default_factory=dict)
    """The parse result written to the audit log beside the exchange."""

    @property
    def ok(self) -> bool:
        return self.value is not None


@dataclass
class Attempt:
    """One turn of the exchange: the reply and the errors it was refused for (none when admitted)."""

    content: str
    errors: list[str]
    exchange_id: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"exchange_id": self.exchange_id, "admitted": not self.errors, "errors": self.errors}


@dataclass
class Dialogue(Generic[T]):
    """The outcome: the first admitted value (None when every attempt was refused) and every attempt."""

    value: T | None
    attempts: list[Attempt]
    last: Verdict[T] | None = None
    """The verdict on the last reply (for callers that keep more than the value, e.g. refused candidates)."""

    @property
    def retries(self) -> int:
        return max(len(self.attempts) - 1, 0)


def reads_followups(backend: LLMBackend) -> bool:
    """Whether a follow-up turn can change the answer: false for the offline engineer, whatever wraps it."""
    layer: Any = backend
    while layer is not None:
        if isinstance(layer, OfflineEngineer):
            return False
        layer = getattr(layer, "inner", None)
    return True


def feedback_message(errors: list[str]) -> str:
    """The follow-up turn that sends a refused reply's errors back to the model."""
    shown = errors[:MAX_FEEDBACK_LINES]
    more = len(errors) - len(shown)
    listing = "\n".join(f"- {e}" for e in shown) + (f"\n- ... and {more} more" if more > 0 else "")
    text = resources.files("mira.engineer").joinpath("prompts", "followup.txt").read_text(encoding="utf-8")
    return Template(text).substitute(errors=listing).strip()


def converse(
    backend: LLMBackend,
    request: LLMRequest,
    judge: Callable[[str], Verdict[T]],
    followups: int,
) -> Dialogue[T]:
    """Ask, judge the reply, and send a refused one back with its errors up to ``followups`` times.

    Errors raised by the backend (unavailable, budget spent) propagate: the caller decides what a
    missing answer means. Each attempt's verdict is attached to its exchange in the audit log.
    """
    turns = followups if reads_followups(backend) else 0
    record = getattr(backend, "record_parse_result", None)
    messages = list(request.messages)
    attempts: list[Attempt] = []
    verdict: Verdict[T] | None = None
    for turn in range(turns + 1):
        ask = request if turn == 0 else replace(request, messages=list(messages))
        reply: LLMReply = backend.complete(ask)
        verdict = judge(reply.content)
        if record is not None and reply.exchange_id is not None:
            record(reply, {**verdict.record, "attempt": turn + 1, "admitted": verdict.ok,
                           **({} if verdict.ok else {"errors": verdict.errors})})
        attempts.append(Attempt(reply.content, [] if verdict.ok else verdict.errors, reply.exchange_id))
        if verdict.ok:
            return Dialogue(verdict.value, attempts, verdict)
        messages += [{"role": "assistant", "content": reply.content},
                     {"role": "user", "content": feedback_message(verdict.errors)}]
    return Dialogue(None, attempts, verdict)
