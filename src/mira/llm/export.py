"""``mira llm export``: a run's exchanges with its reward engineer, as a script or a response cache.

A run directory's audit log (``RUN_DIR/llm/exchanges.jsonl``, see :mod:`mira.llm.audit`) holds every
request and reply. Exported, it lets anyone replay the run without the endpoint, its key or its bill:

* ``script`` (default): a JSON Lines file for ``--llm script:FILE``, one line per reply in call order::

      {"content": REPLY, "purpose": "lsfs", "backend": ..., "model": ..., "engineer": ...,
       "parse_result": ..., "prompt_sha256": ..., "usage": {...}}

  The script backend reads ``content`` and ``usage`` (so token budgets replay too) and ignores the
  rest, which is there for the reader: who answered, what the caller made of it, and
  ``prompt_sha256``, the SHA-256 of the canonical JSON of the request's messages (a list of
  ``{"content", "role"}`` objects, keys sorted, no spaces, UTF-8), to check that a replayed call was
  asked the same question. A script answers every call in order whatever it asks, so a request asked
  again after an earlier answer gets no line (the replay's own cache answers it again, as the run's
  did), and a call that failed at the endpoint is the one thing a script cannot replay.
* ``cache``: a :class:`~mira.llm.cache.ResponseCache` directory holding every answered request under
  the key the run's backend computes, for ``--llm SPEC --llm-cache DIR --llm-offline-only``. The key
  names the backend and model, so the replay must use the same ``--llm`` spec, which is printed.

Exchanges that got no reply are skipped and counted. Nothing is written until the whole log has been
read and checked, and every file is written atomically.
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.llm.audit import EXCHANGES_FILE
from mira.llm.base import PURPOSES, LLMReply, LLMRequest, TokenUsage
from mira.llm.cache import ResponseCache, cache_key
from mira.runio.atomic import atomic_write_text

FORMATS: tuple[str, ...] = ("script", "cache")
DEFAULT_SCRIPT = Path("llm") / "script.jsonl"

# Failures raised before the engineer is asked: a replay meets them again without consuming a reply.
_NOT_ASKED = {"LLMBudgetExceededError", "LLMCacheMissError", "ScriptExhaustedError"}


def prompt_sha256(messages: list[dict[str, str]]) -> str:
    """SHA-256 hex digest of the canonical JSON of ``messages`` (roles and contents only)."""
    canonical = json.dumps(
        [{"role": m["role"], "content": m["content"]} for m in messages],
        sort_keys=True, separators=(",", ":"), ensure_ascii=False,
    )
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def replay_spec(backend: str, model: str) -> str:
    """The ``--llm`` spec whose cache keys are those of replies written by ``backend``/``model``."""
    if backend == "offline":
        return "offline"
    return f"{backend}:{model}"


@dataclass(frozen=True)
class Exchange:
    """One exchange record of the audit log, its parse result merged, and the request rebuilt from it."""

    line: int
    record: dict[str, Any]
    request: LLMRequest

    @property
    def reply(self) -> str | None:
        """The reply's text, or None when the call failed (or answered nothing usable)."""
        reply = self.record.get("reply")
        return reply if isinstance(reply, str) and reply.strip() else None

    @property
    def key(self) -> str:
        return cache_key(str(self.record["backend"]), str(self.record["model"]), self.request)


@dataclass
class ExportResult:
    """What an export wrote and skipped, for the summary line."""

    out: Path
    format: str
    written: Counter[str] = field(default_factory=Counter)
    skipped: Counter[str] = field(default_factory=Counter)
    repeats: int = 0  # script: cache hits on a request answered earlier (no line); cache: duplicate keys
    conflicts: int = 0  # cache: a repeated request whose reply differed (the first is kept)
    unreplayable: Counter[str] = field(default_factory=Counter)  # script: endpoint failures, by error type
    specs: list[str] = field(default_factory=list)
    torn_line: int | None = None

    def summary(self) -> str:
        """One line: how many exchanges went where, by purpose; then how to replay them."""
        what = "exchanges" if sum(self.written.values()) != 1 else "exchange"
        parts = [f"mira llm export: wrote {sum(self.written.values())} {what} ({_by_purpose(self.written)}) "
                 f"as {'a script' if self.format == 'script' else 'cache entries'} to {self.out}",
                 f"skipped {sum(self.skipped.values())} without a reply" +
                 (f" ({_by_purpose(self.skipped)})" if self.skipped else "")]
        if self.repeats and self.format == "script":
            parts.append(f"{self.repeats} repeated request(s) left to the replay's cache (no line)")
        if self.repeats and self.format == "cache":
            parts.append(f"{self.repeats} repeated request(s) share an entry"
                         + (f", {self.conflicts} with a different reply (the first is kept)" if self.conflicts else ""))
        if self.torn_line is not None:
            parts.append(f"ignored the torn last line {self.torn_line} (an interrupted write)")
        lines = ["; ".join(parts)]
        if self.format == "script":
            lines.append(f"replay with: mira train ... --llm script:{self.out}")
            if self.unreplayable:
                kinds = ", ".join(f"{n} {kind}" for kind, n in sorted(self.unreplayable.items()))
                lines.append(f"note: the run had failed calls ({kinds}) that a script answers like any other, "
                             "shifting the replies after them; --format cache replays those exactly")
        else:
            for spec in self.specs:
                lines.append(f"replay with: mira train ... --llm {spec} --llm-cache {self.out} --llm-offline-only"
                             + (f" (script:FILE with a script file named {spec[7:]})"
                                if spec.startswith("script:") else ""))
        return "\n".join(lines)


def _by_purpose(counts: Counter[str]) -> str:
    order = [*PURPOSES, *sorted(set(counts) - set(PURPOSES))]
    return ", ".join(f"{p} {counts[p]}" for p in order if counts[p]) or "none"


def read_exchanges(run_dir: str | Path) -> tuple[list[Exchange], int | None]:
    """Every exchange of ``run_dir``'s audit log in order, and the number of a torn last line (or None).

    A missing run directory or log, a line that is not JSON (other than a torn, unterminated last one,
    which an interrupted append leaves and the run's own reader drops too) or an exchange record that
    cannot be rebuilt into a request is a :class:`UsageError` naming the path and line.
    """
    root = Path(run_dir)
    if not root.is_dir():
        raise UsageError(f"{root}: no such run directory")
    path = root / EXCHANGES_FILE
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise UsageError(f"{path}: no audit log of LLM exchanges in this run directory") from None
    except IsADirectoryError:
        raise UsageError(f"{path}: is a directory, not an audit log") from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot read the audit log ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise UsageError(f"{path}: not UTF-8 text ({exc})") from exc
    lines = text.split("\n")
    exchanges: list[Exchange] = []
    by_id: dict[str, Exchange] = {}
    torn: int | None = None
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        where = f"{path}, line {number}"
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            if number == len(lines):  # unterminated last line: an append that was interrupted
                torn = number
                break
            raise UsageError(f"{where}: not valid JSON ({exc.msg}, column {exc.colno})") from None
        if not isinstance(rec, dict):
            raise UsageError(f"{where}: expected a JSON object, not {type(rec).__name__}")
        if rec.get("kind") == "exchange":
            exchange = Exchange(number, {**rec}, _rebuild_request(rec, where))
            exchanges.append(exchange)
            by_id[str(rec.get("id"))] = exchange
        elif rec.get("kind") == "parse_result" and str(rec.get("exchange_id")) in by_id:
            by_id[str(rec["exchange_id"])].record["parse_result"] = rec.get("parse_result")
    return exchanges, torn


def _rebuild_request(rec: dict[str, Any], where: str) -> LLMRequest:
    """The request an exchange record logged, exactly as its cache key saw it (values as recorded)."""
    try:
        for name in ("backend", "model"):
            if not isinstance(rec.get(name), str):
                raise ValueError(f"'{name}' must be a string")
        decoding = rec.get("decoding") or {}
        messages = rec["messages"]
        if not isinstance(decoding, dict) or not isinstance(messages, list):
            raise ValueError("'messages' must be a list and 'decoding' an object")
        usage = rec.get("usage")
        TokenUsage.from_dict(usage if isinstance(usage, dict) else None)
        float(rec.get("latency_s") or 0.0)
        return LLMRequest(
            messages=[dict(m) for m in messages],
            purpose=rec["purpose"],
            temperature=decoding.get("temperature", 0.0),
            max_tokens=decoding.get("max_tokens"),
            seed=decoding.get("seed"),
            context=rec.get("context") or {},
        )
    except KeyError as exc:
        raise UsageError(f"{where}: exchange record without {exc}") from None
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{where}: not a usable exchange record ({exc})") from None


def export_run(run_dir: str | Path, out: str | Path | None = None, fmt: str = "script") -> ExportResult:
    """Write ``run_dir``'s answered exchanges to ``out`` as a script file or a cache directory."""
    if fmt not in FORMATS:
        raise UsageError(f"unknown export format {fmt!r}: expected one of {', '.join(FORMATS)}")
    exchanges, torn = read_exchanges(run_dir)
    if out is None:
        if fmt == "cache":
            raise UsageError("--format cache needs --out DIR, the cache directory to write")
        out = Path(run_dir) / DEFAULT_SCRIPT
    target = Path(out)
    result = ExportResult(out=target, format=fmt, torn_line=torn)
    answered = []
    for ex in exchanges:
        if ex.reply is None:
            result.skipped[str(ex.record["purpose"])] += 1
            error = ex.record.get("error")
            kind = error.get("type") if isinstance(error, dict) else None
            if kind not in _NOT_ASKED:
                result.unreplayable[str(kind or "no reply")] += 1
        else:
            answered.append(ex)
    if not answered:
        raise UsageError(f"{Path(run_dir) / EXCHANGES_FILE}: no exchange got a reply "
                         f"({len(exchanges)} recorded): nothing to export")
    if fmt == "script":
        _write_script(target, answered, result, run_dir)
    else:
        _write_cache(target, answered, result)
    return result


def _write_script(target: Path, answered: list[Exchange], result: ExportResult, run_dir: str | Path) -> None:
    if target.is_dir():
        raise UsageError(f"--out {target}: is a directory; a script is one file")
    if target.resolve() == (Path(run_dir) / EXCHANGES_FILE).resolve():
        raise UsageError(f"--out {target}: is the run's audit log itself")
    seen: set[str] = set()
    lines = []
    for ex in answered:
        # The replay's own cache answers a request asked before (messages and decoding as a script's key
        # sees them), so the script holds one line per distinct request, as the run's cache did.
        key = cache_key("script", "", ex.request)
        if key in seen:
            result.repeats += 1
            continue
        seen.add(key)
        rec = ex.record
        line: dict[str, Any] = {
            "content": ex.reply, "purpose": rec["purpose"], "backend": rec["backend"], "model": rec["model"],
            "engineer": rec.get("engineer"), "parse_result": rec.get("parse_result"),
            "prompt_sha256": prompt_sha256(ex.request.messages),
        }
        if isinstance(rec.get("usage"), dict):
            line["usage"] = TokenUsage.from_dict(rec["usage"]).to_dict()
        lines.append(json.dumps(line, ensure_ascii=False))
        result.written[str(rec["purpose"])] += 1
    atomic_write_text(target, "\n".join(lines) + "\n")


def _write_cache(target: Path, answered: list[Exchange], result: ExportResult) -> None:
    if target.exists() and not target.is_dir():
        raise UsageError(f"--out {target}: is a file; a cache is a directory")
    cache = ResponseCache(target)
    stored: dict[str, str] = {}
    for ex in answered:
        rec, key, content = ex.record, ex.key, ex.reply
        assert content is not None
        result.written[str(rec["purpose"])] += 1
        spec = replay_spec(rec["backend"], rec["model"])
        if spec not in result.specs:
            result.specs.append(spec)
        if key in stored:
            result.repeats += 1
            result.conflicts += stored[key] != content
            continue
        stored[key] = content
        attempts = rec.get("attempts")
        reply = LLMReply(
            content=content, backend=rec["backend"], model=rec["model"],
            usage=TokenUsage.from_dict(rec.get("usage") if isinstance(rec.get("usage"), dict) else None),
            latency_s=float(rec.get("latency_s") or 0.0), cached=False,
            attempts=attempts if isinstance(attempts, int) and attempts > 0 else 1,
            finish_reason=rec.get("finish_reason"),
        )
        cache.put(key, ex.request, reply)
