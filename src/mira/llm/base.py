"""What every LLM backend speaks: the request, the reply, the backend protocol and the typed errors.

MIRA asks a "reward engineer" for text twice over: LSFS (the initial factor program) and SRR (edit
candidates); the LaRe baseline asks once more. The engineer may be a real LLM behind an
OpenAI-compatible endpoint, a script of canned replies, or the offline rule-based engineer. All of
them take an :class:`LLMRequest` and give an :class:`LLMReply`, so that caching, budgets and the
audit log are wrappers written once (see ``cache.py``, ``budget.py``, ``audit.py``).

Errors are typed because callers must react differently: an endpoint that is down
(:class:`LLMUnavailableError`) lets SRR back off and training go on, while a rejected request
(:class:`LLMRequestRejectedError`) is a bug or a bad key that retrying cannot fix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

from mira.errors import MiraError, UsageError

Purpose = Literal["lsfs", "srr", "lare"]
PURPOSES: tuple[str, ...] = ("lsfs", "srr", "lare")
ROLES: tuple[str, ...] = ("system", "user", "assistant")

#: How the offline engineer is named wherever it appears (audit records, replies, reports), so that
#: nobody mistakes a rule-based answer for an LLM's.
OFFLINE_ENGINEER_LABEL = "offline rule-based reward engineer (not an LLM)"


class LLMError(MiraError):
    """Base class of every error raised while asking a reward engineer (LLM or not) for text."""

    #: How many requests were sent before the error (0 when the call never reached a backend).
    attempts: int = 0


class LLMUnavailableError(LLMError):
    """Every try failed for a transient reason (connection, timeout, HTTP 429 or 5xx).

    ``cause`` is the last underlying exception; callers treat this as "no answer this time" and
    fall back (SRR keeps the current program), never as a verdict on the prompt.
    """

    def __init__(self, message: str, *, cause: BaseException | None = None, attempts: int = 0) -> None:
        super().__init__(message)
        self.cause = cause
        self.attempts = attempts


class LLMRequestRejectedError(LLMError):
    """The endpoint refused the request with a non-retryable status (400, 401, 403, 404, ...).

    Retrying would only repeat the refusal, so it is raised after the first answer.
    """

    def __init__(self, message: str, *, status_code: int | None = None, attempts: int = 1) -> None:
        super().__init__(message)
        self.status_code = status_code
        self.attempts = attempts


class LLMBadReplyError(LLMError):
    """The backend answered, but with nothing usable (empty or whitespace-only content, no choices).

    An empty string must never travel on as if it were a program: downstream parsers would report a
    confusing schema error, or worse, an empty candidate list could read as "no edits needed".
    """

    def __init__(self, message: str, *, attempts: int = 1) -> None:
        super().__init__(message)
        self.attempts = attempts


class LLMBudgetExceededError(LLMError):
    """The run's budget of calls or tokens is spent; raised before the call is made."""


class LLMCacheMissError(LLMError):
    """Offline-only (replay) mode was asked for a request that is not in the cache."""

    def __init__(self, message: str, *, key: str) -> None:
        super().__init__(message)
        self.key = key


class ScriptExhaustedError(LLMError):
    """A scripted backend was asked for more replies than its file holds."""


class ScriptFormatError(LLMError, UsageError):
    """A script file is unreadable or a line is not ``{"content": "..."}``; names the line."""


@dataclass(frozen=True)
class TokenUsage:
    """Tokens billed for one call, as the endpoint reported them (0 when it reports nothing)."""

    prompt_tokens: int = 0
    completion_tokens: int = 0

    @property
    def total_tokens(self) -> int:
        return self.prompt_tokens + self.completion_tokens

    def to_dict(self) -> dict[str, int]:
        return {"prompt_tokens": self.prompt_tokens, "completion_tokens": self.completion_tokens}

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> TokenUsage:
        data = data or {}
        return cls(int(data.get("prompt_tokens") or 0), int(data.get("completion_tokens") or 0))


@dataclass(frozen=True)
class LLMRequest:
    """One question to a reward engineer.

    ``messages`` and the decoding parameters are everything an LLM sees and everything the cache
    key is made of. ``context`` holds the structured facts the prompt was rendered from (task card,
    current program, diagnostics); only the offline engineer reads it, because it cannot read prose.
    The caller must render every fact it puts in ``context`` into the messages too, otherwise two
    requests with equal messages but different contexts would share one cache entry.
    """

    messages: list[dict[str, str]]
    purpose: Purpose = "lsfs"
    temperature: float = 0.0
    max_tokens: int | None = None
    seed: int | None = None
    context: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.purpose not in PURPOSES:
            raise ValueError(f"LLM request purpose must be one of {PURPOSES}, not {self.purpose!r}")
        if not self.messages:
            raise ValueError("an LLM request needs at least one message")
        for i, msg in enumerate(self.messages):
            if not isinstance(msg, dict) or set(msg) != {"role", "content"}:
                raise ValueError(f"message {i} must be a dict with exactly the keys 'role' and 'content'")
            if msg["role"] not in ROLES or not isinstance(msg["content"], str):
                raise ValueError(f"message {i}: role must be one of {ROLES} and content a string")
        if not (math.isfinite(self.temperature) and self.temperature >= 0.0):
            raise ValueError(f"temperature must be a finite number >= 0, not {self.temperature!r}")
        if self.max_tokens is not None and self.max_tokens <= 0:
            raise ValueError(f"max_tokens must be positive, not {self.max_tokens!r}")

    def decoding(self) -> dict[str, Any]:
        """The decoding parameters, as they enter the cache key and the audit log."""
        return {"temperature": self.temperature, "max_tokens": self.max_tokens, "seed": self.seed}

    def to_dict(self) -> dict[str, Any]:
        return {
            "purpose": self.purpose,
            "messages": [dict(m) for m in self.messages],
            "decoding": self.decoding(),
            "context": self.context,
        }


@dataclass(frozen=True)
class LLMReply:
    """What a backend answered, with enough bookkeeping to audit and budget it.

    ``content`` is returned verbatim (prose, code fences and all): extracting the JSON is the
    caller's job, and the audit log must show what the engineer really said.
    ``attempts`` counts HTTP requests sent (0 for a cache hit). ``exchange_id`` is set by
    :class:`mira.llm.audit.AuditedBackend` so the caller can attach its parse result later.
    """

    content: str
    backend: str
    model: str
    usage: TokenUsage = field(default_factory=TokenUsage)
    latency_s: float = 0.0
    cached: bool = False
    attempts: int = 1
    finish_reason: str | None = None
    exchange_id: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "content": self.content,
            "backend": self.backend,
            "model": self.model,
            "usage": self.usage.to_dict(),
            "latency_s": self.latency_s,
            "cached": self.cached,
            "attempts": self.attempts,
            "finish_reason": self.finish_reason,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LLMReply:
        return cls(
            content=str(data["content"]),
            backend=str(data["backend"]),
            model=str(data["model"]),
            usage=TokenUsage.from_dict(data.get("usage")),
            latency_s=float(data.get("latency_s") or 0.0),
            cached=bool(data.get("cached", False)),
            attempts=int(data.get("attempts", 1)),
            finish_reason=data.get("finish_reason"),
        )


@runtime_checkable
class LLMBackend(Protocol):
    """Anything that answers an :class:`LLMRequest`.

    ``name`` is the backend kind ("openai", "script", "offline") and ``model`` what answers within
    it; both enter the cache key, so replies of different engineers never mix.
    """

    @property
    def name(self) -> str: ...

    @property
    def model(self) -> str: ...

    def complete(self, request: LLMRequest) -> LLMReply: ...


class WrappedBackend:
    """A backend that answers by asking ``inner`` (the cache, the budget, the audit log around it).

    It speaks as ``inner``: ``name`` and ``model`` are ``inner``'s, so a wrapper changes neither the
    cache key nor who a reply is recorded as written by.
    """

    inner: LLMBackend

    @property
    def name(self) -> str:
        return self.inner.name

    @property
    def model(self) -> str:
        return self.inner.model


def require_content(content: str | None, *, backend: str, model: str, attempts: int = 1) -> str:
    """Return ``content`` unchanged, or raise :class:`LLMBadReplyError` if it is empty or blank."""
    if content is None or not content.strip():
        raise LLMBadReplyError(
            f"{backend}:{model} returned an empty reply (an empty reply is never a program)",
            attempts=attempts,
        )
    return content


def engineer_label(backend: str, model: str) -> str:
    """A plain statement of who wrote a reply, for audit records and reports."""
    if backend == "offline":
        return OFFLINE_ENGINEER_LABEL
    if backend == "script":
        return f"scripted replies from {model} (not an LLM)"
    return f"LLM {model} via {backend}"
