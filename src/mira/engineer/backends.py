"""Build a ready-to-use backend from a ``--llm`` spec, with cache, budget and audit wrapped around it.

The layering is fixed here so no caller gets it wrong::

    AuditedBackend( CachedBackend( BudgetedBackend( offline | script:FILE | openai:MODEL )))

Audit is outermost so cache hits and refusals are logged too; the budget is innermost so replays
from the cache cost nothing. Each layer is present only when asked for: the cache when
``cache_dir`` is given (callers pass their default directory, so it is on by default), the budget
when a limit is set, the audit log when ``audit_dir`` (the run directory) is given.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

from mira.engineer.offline import OfflineEngineer
from mira.errors import UsageError
from mira.llm.audit import AuditedBackend, AuditLog
from mira.llm.base import LLMBackend
from mira.llm.budget import BudgetedBackend
from mira.llm.cache import CachedBackend
from mira.llm.script import ScriptBackend

SPEC_HELP = "expected offline, script:FILE or openai:MODEL"

T = TypeVar("T")


def make_backend(
    spec: str,
    *,
    base_url: str | None = None,
    api_key_env: str = "OPENAI_API_KEY",
    cache_dir: str | Path | None = None,
    offline_only: bool = False,
    audit_dir: str | Path | None = None,
    max_calls: int | None = None,
    max_tokens_total: int | None = None,
    timeout_s: float = 60,
    max_retries: int = 4,
) -> LLMBackend:
    """Parse ``spec`` and wrap the backend; a bad spec or option is a one-line ``UsageError``."""
    kind, sep, arg = spec.strip().partition(":")
    inner: LLMBackend
    if kind == "offline" and not sep:
        inner = OfflineEngineer()
    elif kind == "script" and sep:
        if not arg.strip():
            raise UsageError(f"LLM backend {spec!r}: script needs a file, script:FILE")
        inner = ScriptBackend(Path(arg).expanduser())
    elif kind == "openai" and sep:
        if not arg.strip():
            raise UsageError(f"LLM backend {spec!r}: openai needs a model, openai:MODEL")
        from mira.llm.openai_backend import OpenAIBackend  # the SDK is slow to import: only when used

        inner = OpenAIBackend(
            arg.strip(),
            base_url=base_url,
            api_key_env=api_key_env,
            timeout_s=timeout_s,
            max_retries=max_retries,
        )
    else:
        raise UsageError(f"unknown LLM backend {spec!r}: {SPEC_HELP}")
    for label, limit in (("max_calls", max_calls), ("max_tokens_total", max_tokens_total)):
        if limit is not None and limit < 0:
            raise UsageError(f"LLM budget {label} must be >= 0, not {limit}")
    if offline_only and cache_dir is None:
        raise UsageError("offline-only LLM replay needs a cache directory to replay from")
    backend: LLMBackend = inner
    if max_calls is not None or max_tokens_total is not None:
        backend = BudgetedBackend(backend, max_calls=max_calls, max_tokens_total=max_tokens_total)
    if cache_dir is not None:
        backend = CachedBackend(backend, cache_dir, offline_only=offline_only)
    if audit_dir is not None:
        backend = AuditedBackend(backend, AuditLog(audit_dir))
    return backend


def layers(backend: Any) -> list[Any]:
    """The wrapper chain from outermost to the innermost backend."""
    out = [backend]
    while hasattr(out[-1], "inner"):
        out.append(out[-1].inner)
    return out


def find_layer(backend: Any, kind: type[T]) -> T | None:
    """The first layer of type ``kind`` (e.g. ``BudgetedBackend``), or None."""
    for layer in layers(backend):
        if isinstance(layer, kind):
            return layer
    return None


def backend_state_dict(backend: Any) -> dict[str, Any]:
    """Checkpointable state of every stateful layer (budget counters, script position)."""
    return {
        type(layer).__name__: layer.state_dict() for layer in layers(backend) if hasattr(layer, "state_dict")
    }


def load_backend_state_dict(backend: Any, state: dict[str, Any]) -> None:
    """Restore what :func:`backend_state_dict` saved into the matching layers."""
    for layer in layers(backend):
        saved = state.get(type(layer).__name__)
        if saved is not None and hasattr(layer, "load_state_dict"):
            layer.load_state_dict(saved)
