"""On-disk response cache, so a run can be replayed offline and reproduced exactly.

The key is the SHA-256 of the canonical JSON of (backend name, model, messages, decoding
parameters): exactly what decides an answer at temperature 0, and nothing else (``context`` and
``purpose`` are deliberately left out; the messages already carry what the engineer is told).
Each entry is its own file, ``CACHE_DIR/<key[:2]>/<key>.json``, written atomically, holding the full
request and reply for audit. One file per entry means concurrent runs sharing a cache never
rewrite each other's entries, and a killed run never leaves a half-written cache.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from mira.llm.base import LLMBackend, LLMCacheMissError, LLMReply, LLMRequest, WrappedBackend
from mira.runio.atomic import atomic_write_json

log = logging.getLogger(__name__)

CACHE_FORMAT = 1


def cache_key(backend: str, model: str, request: LLMRequest) -> str:
    """SHA-256 hex digest of the canonical JSON of what determines the reply."""
    payload = {
        "backend": backend,
        "model": model,
        "messages": [{"role": m["role"], "content": m["content"]} for m in request.messages],
        "decoding": request.decoding(),
    }
    if backend == "offline":
        # The rule-based engineer reads the request's structured context, not its prose: the context
        # determines its reply (an LLM's is determined by the messages, which restate the context).
        payload["context"] = request.context
    canonical = json.dumps(payload, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


class ResponseCache:
    """A directory of cache entries, one JSON file per key."""

    def __init__(self, cache_dir: str | Path) -> None:
        self.root = Path(cache_dir)

    def path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.json"

    def get(self, key: str) -> dict[str, Any] | None:
        """The stored entry, or None when absent or unreadable (an unreadable entry is rewritten)."""
        target = self.path(key)
        try:
            entry = json.loads(target.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            log.warning("ignoring unreadable LLM cache entry %s: %s", target, exc)
            return None
        if not isinstance(entry, dict) or entry.get("key") != key or not isinstance(entry.get("reply"), dict):
            log.warning("ignoring malformed LLM cache entry %s", target)
            return None
        return entry

    def put(self, key: str, request: LLMRequest, reply: LLMReply) -> None:
        atomic_write_json(
            self.path(key),
            {
                "format": CACHE_FORMAT,
                "key": key,
                "stored_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "request": {"backend": reply.backend, "model": reply.model, **request.to_dict()},
                "reply": reply.to_dict(),
            },
        )


class CachedBackend(WrappedBackend):
    """Answer from the cache when possible; otherwise ask ``inner`` and store its reply.

    A hit never calls ``inner`` and comes back with ``cached=True`` and ``attempts=0``. With
    ``offline_only`` a miss is an :class:`LLMCacheMissError` naming the key, so a replay can
    never silently reach the network. Errors are not cached: the next run asks again.
    """

    def __init__(self, inner: LLMBackend, cache_dir: str | Path, *, offline_only: bool = False) -> None:
        self.inner = inner
        self.cache = ResponseCache(cache_dir)
        self.offline_only = offline_only

    def key(self, request: LLMRequest) -> str:
        return cache_key(self.inner.name, self.inner.model, request)

    def complete(self, request: LLMRequest) -> LLMReply:
        started = time.monotonic()
        key = self.key(request)
        entry = self.cache.get(key)
        if entry is not None:
            stored = LLMReply.from_dict(entry["reply"])
            return replace(stored, cached=True, attempts=0, latency_s=time.monotonic() - started)
        if self.offline_only:
            raise LLMCacheMissError(
                f"offline-only: no cached reply for key {key} ({self.inner.name}:{self.inner.model}, "
                f"purpose {request.purpose}) in {self.cache.root}",
                key=key,
            )
        reply = self.inner.complete(request)
        self.cache.put(key, request, replace(reply, cached=False, exchange_id=None))
        return reply
