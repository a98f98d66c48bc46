"""Which reward engineer answers, and how its calls are made (``TrainConfig.llm``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class LLMConfig:
    """Which reward engineer writes and edits factor programs, and how calls are made."""

    backend: str = "offline"
    """``offline`` (rule-based engineer, no network), ``script:FILE`` or ``openai:MODEL``."""
    base_url: str | None = None
    """Endpoint of an OpenAI-compatible server (default: ``$MIRA_BASE_URL`` or the SDK's)."""
    api_key_env: str = "OPENAI_API_KEY"
    """Name of the environment variable holding the API key (the key itself is never saved)."""
    cache_dir: str | None = None
    """Response cache; default ``RUN_DIR/llm/cache``."""
    offline_only: bool = False
    """Turn a cache miss into an error instead of a call (exact offline replay)."""
    timeout_s: float = 120.0
    """Per-request timeout."""
    max_retries: int = 4
    """Retries on connection errors, timeouts, 429 and 5xx, with exponential backoff and jitter."""
    followups: int = 2
    """Times a refused reply (unparsable, or failing the checks) is sent back with its errors before the
    caller falls back; each follow-up is a call in the budget. The offline engineer gets none."""
    max_calls: int | None = 200
    """Per-run budget on LLM calls (None: unlimited)."""
    max_tokens_total: int | None = 2_000_000
    """Per-run budget on prompt + completion tokens (None: unlimited)."""
