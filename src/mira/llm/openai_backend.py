"""``openai:MODEL`` — any OpenAI-compatible chat endpoint through the official ``openai`` SDK.

DeepSeek (as in the paper), OpenAI, vLLM, Ollama and llama.cpp all speak ``/v1/chat/completions``.
The SDK's own retries are switched off (``max_retries=0``) and done here instead, so that every
attempt, every backoff sleep and the final cause are visible to the audit log and to tests (which
inject ``sleep`` and ``rng``). Transient failures — connection errors, timeouts, HTTP 408/429/5xx —
are retried with capped exponential backoff and jitter, honouring ``Retry-After``; any other 4xx is
raised at once as :class:`LLMRequestRejectedError`, since repeating it cannot help.
"""

from __future__ import annotations

import email.utils
import os
import random
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlparse

import openai

from mira.errors import UsageError
from mira.llm.base import (
    LLMBadReplyError,
    LLMReply,
    LLMRequest,
    LLMRequestRejectedError,
    LLMUnavailableError,
    TokenUsage,
    require_content,
)

DEFAULT_BASE_URL = "https://api.openai.com/v1"
BASE_URL_ENV = "MIRA_BASE_URL"
#: Sent as the key to local servers (vLLM, Ollama, llama.cpp) that need none.
DUMMY_LOCAL_KEY = "sk-local-no-key-required"
_LOCAL_HOSTS = frozenset({"localhost", "127.0.0.1", "::1", "0.0.0.0"})
_RETRYABLE_STATUS = frozenset({408, 429})


def is_local_url(url: str) -> bool:
    """True when ``url`` points at this machine, where servers usually need no API key."""
    host = (urlparse(url).hostname or "").lower()
    return host in _LOCAL_HOSTS or host.endswith(".localhost")


def resolve_base_url(base_url: str | None) -> str:
    """The endpoint to use: the argument, else ``$MIRA_BASE_URL``, else OpenAI's."""
    url = base_url or os.environ.get(BASE_URL_ENV) or DEFAULT_BASE_URL
    parsed = urlparse(url)
    if parsed.scheme not in ("http", "https") or not parsed.netloc:
        raise UsageError(f"LLM base URL {url!r} is not an http(s) URL")
    return url


def resolve_api_key(api_key_env: str, base_url: str) -> str:
    """Read the key from the environment variable ``api_key_env``; local servers may go without."""
    key = os.environ.get(api_key_env, "").strip()
    if key:
        return key
    if is_local_url(base_url):
        return DUMMY_LOCAL_KEY
    raise UsageError(
        f"no API key for {base_url}: set the environment variable {api_key_env} "
        f"(or choose another with --api-key-env, or use --llm offline)"
    )


def parse_retry_after(headers: Any, now: float | None = None) -> float | None:
    """Seconds to wait as the server asked (``retry-after-ms`` or ``Retry-After``), if it asked."""
    if headers is None:
        return None
    raw_ms = headers.get("retry-after-ms")
    if raw_ms is not None:
        try:
            return max(float(raw_ms) / 1000.0, 0.0)
        except ValueError:
            pass
    raw = headers.get("retry-after")
    if raw is None:
        return None
    try:
        return max(float(raw), 0.0)
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(raw)
    except (TypeError, ValueError):
        return None
    current = time.time() if now is None else now
    return max(when.timestamp() - current, 0.0)


class OpenAIBackend:
    """Chat completions from an OpenAI-compatible endpoint, with observable retries.

    ``max_retries`` is the number of *extra* tries: at most ``1 + max_retries`` requests per call.
    Backoff before retry ``i`` (0-based) is ``min(backoff_max_s, backoff_base_s * 2**i)`` with
    "equal jitter" (half fixed, half uniform), or the server's ``Retry-After`` capped at
    ``retry_after_cap_s``.
    """

    name = "openai"

    def __init__(
        self,
        model: str,
        *,
        base_url: str | None = None,
        api_key_env: str = "OPENAI_API_KEY",
        timeout_s: float = 60.0,
        max_retries: int = 4,
        backoff_base_s: float = 1.0,
        backoff_max_s: float = 30.0,
        retry_after_cap_s: float = 120.0,
        sleep: Callable[[float], None] = time.sleep,
        rng: random.Random | None = None,
    ) -> None:
        if not model.strip():
            raise UsageError("openai backend needs a model name: openai:MODEL")
        if timeout_s <= 0:
            raise UsageError(f"LLM timeout must be positive, not {timeout_s}")
        if max_retries < 0:
            raise UsageError(f"LLM max retries must be >= 0, not {max_retries}")
        self.model = model
        self.base_url = resolve_base_url(base_url)
        self.timeout_s = float(timeout_s)
        self.max_retries = int(max_retries)
        self.backoff_base_s = float(backoff_base_s)
        self.backoff_max_s = float(backoff_max_s)
        self.retry_after_cap_s = float(retry_after_cap_s)
        self._sleep = sleep
        self._rng = rng if rng is not None else random.Random()
        #: Every backoff actually slept, in seconds (for the audit log and tests).
        self.sleeps: list[float] = []
        self._client = openai.OpenAI(
            base_url=self.base_url,
            api_key=resolve_api_key(api_key_env, self.base_url),
            timeout=self.timeout_s,
            max_retries=0,
        )

    def backoff_s(self, retry_index: int, retry_after: float | None) -> float:
        """Delay before retry ``retry_index`` (0-based)."""
        if retry_after is not None:
            return min(retry_after, self.retry_after_cap_s)
        ceiling = min(self.backoff_max_s, self.backoff_base_s * (2.0**retry_index))
        return ceiling / 2.0 + self._rng.uniform(0.0, ceiling / 2.0)

    def _create(self, request: LLMRequest) -> Any:
        kwargs: dict[str, Any] = {
            "model": self.model,
            "messages": [dict(m) for m in request.messages],
            "temperature": request.temperature,
        }
        if request.max_tokens is not None:
            kwargs["max_tokens"] = request.max_tokens
        if request.seed is not None:
            kwargs["seed"] = request.seed
        return self._client.chat.completions.create(**kwargs)

    def complete(self, request: LLMRequest) -> LLMReply:
        """Send the request, retrying transient failures; return the reply content verbatim."""
        started = time.monotonic()
        tries = 1 + self.max_retries
        last: BaseException | None = None
        for attempt in range(1, tries + 1):
            retry_after: float | None = None
            try:
                response = self._create(request)
            except openai.APITimeoutError as exc:
                last = exc
            except openai.APIConnectionError as exc:
                last = exc
            except openai.APIStatusError as exc:
                status = exc.status_code
                if status not in _RETRYABLE_STATUS and status < 500:
                    raise LLMRequestRejectedError(
                        f"{self.base_url} rejected the request to model {self.model!r} "
                        f"with HTTP {status}: {_short(exc.message)}",
                        status_code=status,
                        attempts=attempt,
                    ) from exc
                last = exc
                retry_after = parse_retry_after(exc.response.headers)
            except openai.APIResponseValidationError as exc:
                raise LLMBadReplyError(
                    f"{self.base_url} answered with a malformed body: {_short(exc.message)}", attempts=attempt
                ) from exc
            except ValueError as exc:  # the SDK decoding a body that is not JSON (json.JSONDecodeError)
                raise LLMBadReplyError(
                    f"{self.base_url} answered with a body that is not JSON: {_short(str(exc))}", attempts=attempt
                ) from exc
            else:
                return self._reply(response, attempt, started)
            if attempt < tries:
                delay = self.backoff_s(attempt - 1, retry_after)
                self.sleeps.append(delay)
                self._sleep(delay)
        raise LLMUnavailableError(
            f"{self.base_url} model {self.model!r} unavailable after {tries} tries: {_describe(last)}",
            cause=last,
            attempts=tries,
        ) from last

    def _reply(self, response: Any, attempts: int, started: float) -> LLMReply:
        choices = getattr(response, "choices", None) or []
        if not choices:
            raise LLMBadReplyError(f"{self.base_url} answered without any choices", attempts=attempts)
        choice = choices[0]
        message = getattr(choice, "message", None)
        content = require_content(
            getattr(message, "content", None), backend=self.name, model=self.model, attempts=attempts
        )
        usage = getattr(response, "usage", None)
        return LLMReply(
            content=content,
            backend=self.name,
            model=self.model,
            usage=TokenUsage(
                int(getattr(usage, "prompt_tokens", 0) or 0),
                int(getattr(usage, "completion_tokens", 0) or 0),
            ),
            latency_s=time.monotonic() - started,
            cached=False,
            attempts=attempts,
            finish_reason=getattr(choice, "finish_reason", None),
        )


def _short(text: str, limit: int = 300) -> str:
    one_line = " ".join(str(text).split())
    return one_line if len(one_line) <= limit else one_line[: limit - 3] + "..."


def _describe(exc: BaseException | None) -> str:
    if exc is None:
        return "no attempt was made"
    if isinstance(exc, openai.APIStatusError):
        return f"HTTP {exc.status_code} ({type(exc).__name__})"
    return f"{type(exc).__name__}: {_short(str(exc))}"
