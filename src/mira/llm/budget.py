"""A per-run budget on LLM calls and tokens.

A misbehaving outer loop (a trigger that never cools down) must not run up an unbounded bill, so
the budget is checked *before* each call and refuses with :class:`LLMBudgetExceededError`. Put it
inside the cache (``CachedBackend(BudgetedBackend(inner))``, as ``make_backend`` does) so replays
from the cache cost nothing. Counters are part of the run's checkpoint (``state_dict``), so a
resumed run keeps spending from the same budget instead of starting afresh.

Tokens are only known after a call, so the token limit refuses once the total has been reached:
the last allowed call may overshoot it by that call's own usage.
"""

from __future__ import annotations

from typing import Any

from mira.llm.base import LLMBackend, LLMBudgetExceededError, LLMError, LLMReply, LLMRequest, WrappedBackend


class BudgetedBackend(WrappedBackend):
    """Counts calls and tokens to ``inner`` and refuses calls past ``max_calls`` / ``max_tokens_total``.

    Every call handed to ``inner`` counts, including ones that fail (they may have been billed).
    """

    def __init__(
        self, inner: LLMBackend, *, max_calls: int | None = None, max_tokens_total: int | None = None
    ) -> None:
        if max_calls is not None and max_calls < 0:
            raise ValueError(f"max_calls must be >= 0, not {max_calls}")
        if max_tokens_total is not None and max_tokens_total < 0:
            raise ValueError(f"max_tokens_total must be >= 0, not {max_tokens_total}")
        self.inner = inner
        self.max_calls = max_calls
        self.max_tokens_total = max_tokens_total
        self.calls = 0
        self.failed_calls = 0
        self.prompt_tokens = 0
        self.completion_tokens = 0

    @property
    def total_tokens(self) -> int:
        return self.prompt_tokens + self.completion_tokens

    def check(self, request: LLMRequest) -> None:
        """Raise if one more call would break the budget."""
        if self.max_calls is not None and self.calls >= self.max_calls:
            raise LLMBudgetExceededError(
                f"LLM budget exceeded: {self.calls} of {self.max_calls} calls used "
                f"(purpose {request.purpose} refused)"
            )
        if self.max_tokens_total is not None and self.total_tokens >= self.max_tokens_total:
            raise LLMBudgetExceededError(
                f"LLM budget exceeded: {self.total_tokens} of {self.max_tokens_total} tokens used "
                f"(purpose {request.purpose} refused)"
            )

    def complete(self, request: LLMRequest) -> LLMReply:
        self.check(request)
        self.calls += 1
        try:
            reply = self.inner.complete(request)
        except LLMError:
            self.failed_calls += 1
            raise
        self.prompt_tokens += reply.usage.prompt_tokens
        self.completion_tokens += reply.usage.completion_tokens
        return reply

    def usage(self) -> dict[str, Any]:
        """Counters and limits, for logs and reports."""
        return {
            "calls": self.calls,
            "failed_calls": self.failed_calls,
            "prompt_tokens": self.prompt_tokens,
            "completion_tokens": self.completion_tokens,
            "total_tokens": self.total_tokens,
            "max_calls": self.max_calls,
            "max_tokens_total": self.max_tokens_total,
        }

    def state_dict(self) -> dict[str, int]:
        return {
            "calls": self.calls,
            "failed_calls": self.failed_calls,
            "prompt_tokens": self.prompt_tokens,
            "completion_tokens": self.completion_tokens,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the counters (limits come from the current configuration, not the checkpoint)."""
        self.calls = int(state["calls"])
        self.failed_calls = int(state.get("failed_calls", 0))
        self.prompt_tokens = int(state["prompt_tokens"])
        self.completion_tokens = int(state["completion_tokens"])
