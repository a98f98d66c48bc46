"""Reward engineers behind one interface: an OpenAI-compatible LLM, a script, or the offline rules.

``make_backend("offline" | "script:FILE" | "openai:MODEL", ...)`` returns a backend already wrapped
with the on-disk response cache, the run's call/token budget and the audit log; callers send an
:class:`LLMRequest` and get an :class:`LLMReply` or a typed :class:`LLMError`.
"""

from typing import TYPE_CHECKING, Any

from mira.llm.audit import AuditedBackend, AuditLog
from mira.llm.base import (
    OFFLINE_ENGINEER_LABEL,
    LLMBackend,
    LLMBadReplyError,
    LLMBudgetExceededError,
    LLMCacheMissError,
    LLMError,
    LLMReply,
    LLMRequest,
    LLMRequestRejectedError,
    LLMUnavailableError,
    ScriptExhaustedError,
    ScriptFormatError,
    TokenUsage,
)
from mira.llm.budget import BudgetedBackend
from mira.llm.cache import CachedBackend, cache_key
from mira.llm.factory import backend_state_dict, find_layer, load_backend_state_dict, make_backend
from mira.llm.offline import OfflineEngineer
from mira.llm.script import ScriptBackend

if TYPE_CHECKING:
    from mira.llm.openai_backend import OpenAIBackend


def __getattr__(name: str) -> Any:
    """Import the ``openai`` SDK (about a second) only when the HTTP backend is actually wanted."""
    if name == "OpenAIBackend":
        from mira.llm.openai_backend import OpenAIBackend

        return OpenAIBackend
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "OFFLINE_ENGINEER_LABEL",
    "AuditLog",
    "AuditedBackend",
    "BudgetedBackend",
    "CachedBackend",
    "LLMBackend",
    "LLMBadReplyError",
    "LLMBudgetExceededError",
    "LLMCacheMissError",
    "LLMError",
    "LLMReply",
    "LLMRequest",
    "LLMRequestRejectedError",
    "LLMUnavailableError",
    "OfflineEngineer",
    "OpenAIBackend",
    "ScriptBackend",
    "ScriptExhaustedError",
    "ScriptFormatError",
    "TokenUsage",
    "backend_state_dict",
    "cache_key",
    "find_layer",
    "load_backend_state_dict",
    "make_backend",
]
