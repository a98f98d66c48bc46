"""The audit trail of every exchange with a reward engineer: ``RUN_DIR/llm/exchanges.jsonl``.

The paper logs every SRR directive and LLM output (Appendix A); a reader of a run must be able to
see exactly what was asked, what came back, from whom, at what cost, and what the caller made of
it. Records are appended (one JSON object per line, fsynced) and never rewritten, so the caller's
parse result is a second record pointing back at the exchange; :meth:`AuditLog.read` merges them.
Every record names the engineer plainly, so the offline engine always reads as
"offline rule-based reward engineer (not an LLM)".
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mira.llm.base import LLMBackend, LLMError, LLMReply, LLMRequest, WrappedBackend, engineer_label
from mira.runio.atomic import append_line, read_jsonl

EXCHANGES_FILE = Path("llm") / "exchanges.jsonl"


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _jsonable(value: Any) -> Any:
    """``value`` if it serialises to JSON, else its string form (an audit must never crash a run)."""
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return json.loads(json.dumps(value, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    return value


class AuditLog:
    """Append-only log of exchanges under ``run_dir``."""

    def __init__(self, run_dir: str | Path) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / EXCHANGES_FILE
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._engineers: dict[str, str] = {}

    def _append(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, ensure_ascii=False, separators=(",", ":"))
        with self._lock:
            append_line(self.path, line)

    def record_exchange(
        self,
        request: LLMRequest,
        *,
        backend: str,
        model: str,
        reply: LLMReply | None = None,
        error: BaseException | None = None,
        latency_s: float | None = None,
    ) -> str:
        """Append one exchange (successful or not) and return its id."""
        exchange_id = uuid.uuid4().hex
        self._engineers[exchange_id] = engineer_label(backend, model)
        self._append(
            {
                "kind": "exchange",
                "id": exchange_id,
                "timestamp": _now(),
                "purpose": request.purpose,
                "engineer": engineer_label(backend, model),
                "backend": backend,
                "model": model,
                "messages": [dict(m) for m in request.messages],
                "decoding": request.decoding(),
                "context": _jsonable(request.context),
                "reply": reply.content if reply is not None else None,
                "finish_reason": reply.finish_reason if reply is not None else None,
                "latency_s": reply.latency_s if reply is not None else latency_s,
                "usage": reply.usage.to_dict() if reply is not None else None,
                "cached": reply.cached if reply is not None else False,
                "attempts": reply.attempts if reply is not None else getattr(error, "attempts", None),
                "error": None if error is None else {"type": type(error).__name__, "message": str(error)},
                "parse_result": None,
            }
        )
        return exchange_id

    def record_parse_result(
        self, exchange_id: str, parse_result: Any, *, backend: str | None = None, model: str | None = None
    ) -> None:
        """Attach what the caller made of a reply (parsed OK, schema error, candidates kept...)."""
        record: dict[str, Any] = {
            "kind": "parse_result",
            "exchange_id": exchange_id,
            "timestamp": _now(),
            "parse_result": _jsonable(parse_result),
        }
        engineer = self._engineers.get(exchange_id)
        if engineer is None and backend is not None:
            engineer = engineer_label(backend, model or "")
        if engineer is not None:
            record["engineer"] = engineer
        self._append(record)

    def read(self) -> list[dict[str, Any]]:
        """Every exchange in order, with the latest parse result recorded for it merged in."""
        exchanges: list[dict[str, Any]] = []
        by_id: dict[str, dict[str, Any]] = {}
        for rec in read_jsonl(self.path):
            if rec.get("kind") == "exchange":
                exchanges.append(rec)
                by_id[rec["id"]] = rec
            elif rec.get("kind") == "parse_result" and rec.get("exchange_id") in by_id:
                by_id[rec["exchange_id"]]["parse_result"] = rec["parse_result"]
        return exchanges


class AuditedBackend(WrappedBackend):
    """Logs every call through it, successes and failures alike, then passes the outcome on.

    The reply comes back with ``exchange_id`` set, for :meth:`record_parse_result`.
    """

    def __init__(self, inner: LLMBackend, log: AuditLog) -> None:
        self.inner = inner
        self.log = log

    def complete(self, request: LLMRequest) -> LLMReply:
        started = time.monotonic()
        try:
            reply = self.inner.complete(request)
        except LLMError as exc:
            self.log.record_exchange(
                request, backend=self.name, model=self.model, error=exc, latency_s=time.monotonic() - started
            )
            raise
        exchange_id = self.log.record_exchange(request, backend=reply.backend, model=reply.model, reply=reply)
        return replace(reply, exchange_id=exchange_id)

    def record_parse_result(self, reply: LLMReply | str, parse_result: Any) -> None:
        """Attach the caller's verdict on ``reply`` (or on an exchange id) to the audit log."""
        exchange_id = reply if isinstance(reply, str) else reply.exchange_id
        if exchange_id is None:
            raise ValueError("this reply did not pass through the audit log (no exchange_id)")
        self.log.record_parse_result(exchange_id, parse_result, backend=self.name, model=self.model)
