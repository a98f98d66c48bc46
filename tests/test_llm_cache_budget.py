"""Response cache, offline-only replay, budgets and the audit log around LLM backends."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from chat_server import ChatServer, reply, status
from mira.engineer.backends import make_backend
from mira.engineer.offline import OfflineEngineer
from mira.llm.audit import AuditedBackend, AuditLog
from mira.llm.base import (
    OFFLINE_ENGINEER_LABEL,
    LLMBudgetExceededError,
    LLMCacheMissError,
    LLMReply,
    LLMRequest,
    LLMRequestRejectedError,
    TokenUsage,
)
from mira.llm.budget import BudgetedBackend
from mira.llm.cache import CachedBackend, cache_key
from mira.llm.script import ScriptBackend


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[ChatServer]:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    with ChatServer() as srv:
        yield srv


def _request(text: str = "write factors", **kw: object) -> LLMRequest:
    return LLMRequest(messages=[{"role": "user", "content": text}], purpose="srr", **kw)  # type: ignore[arg-type]


class Counting:
    """A stand-in backend that counts calls and reports fixed token usage."""

    name = "fake"
    model = "m1"

    def __init__(self, tokens: int = 10) -> None:
        self.calls = 0
        self.tokens = tokens

    def complete(self, request: LLMRequest) -> LLMReply:
        self.calls += 1
        return LLMReply(f"answer {self.calls}", self.name, self.model, TokenUsage(self.tokens, self.tokens))


def test_cache_hit_on_rerun_sends_no_request(server: ChatServer, tmp_path: Path) -> None:
    server.push(reply("first", prompt_tokens=30, completion_tokens=4), reply("second"))
    cache = tmp_path / "cache"
    first = make_backend("openai:test-model", base_url=server.url, cache_dir=cache).complete(_request())
    assert first.content == "first" and not first.cached and server.count == 1
    # A new run (fresh backend object) replays from disk: nothing reaches the server.
    rerun = make_backend("openai:test-model", base_url=server.url, cache_dir=cache)
    again = rerun.complete(_request())
    assert again.content == "first" and again.cached and again.attempts == 0
    assert again.usage == TokenUsage(30, 4)
    assert server.count == 1
    # Other messages or decoding parameters are other keys.
    assert rerun.complete(_request(seed=1)).content == "second" and server.count == 2


def test_cache_entry_stores_full_request_and_reply(tmp_path: Path) -> None:
    inner = Counting()
    backend = CachedBackend(inner, tmp_path)
    req = _request(context={"fact": 1})
    backend.complete(req)
    key = cache_key("fake", "m1", req)
    entry = json.loads((tmp_path / key[:2] / f"{key}.json").read_text())
    assert entry["key"] == key
    assert entry["request"]["messages"] == req.messages
    assert entry["request"]["decoding"] == {"temperature": 0.0, "max_tokens": None, "seed": None}
    assert entry["request"]["context"] == {"fact": 1}
    assert entry["reply"]["content"] == "answer 1"


def test_cache_key_ignores_context_and_purpose_but_not_model() -> None:
    a = _request(context={"x": 1})
    b = LLMRequest(messages=a.messages, purpose="lsfs", context={"x": 2})
    assert cache_key("openai", "m", a) == cache_key("openai", "m", b)
    assert cache_key("openai", "m", a) != cache_key("openai", "m2", a)
    assert cache_key("openai", "m", a) != cache_key("script", "m", a)
    assert cache_key("openai", "m", a) != cache_key("openai", "m", _request(temperature=0.5))


def test_corrupt_cache_entry_is_a_miss_and_rewritten(tmp_path: Path) -> None:
    inner = Counting()
    backend = CachedBackend(inner, tmp_path)
    req = _request()
    path = backend.cache.path(backend.key(req))
    path.parent.mkdir(parents=True)
    path.write_text("{torn")
    assert backend.complete(req).content == "answer 1" and inner.calls == 1
    assert backend.complete(req).cached and inner.calls == 1


def test_offline_only_cache_miss_names_the_key(server: ChatServer, tmp_path: Path) -> None:
    server.push(reply("never"))
    backend = make_backend("openai:test-model", base_url=server.url, cache_dir=tmp_path, offline_only=True)
    req = _request()
    with pytest.raises(LLMCacheMissError) as info:
        backend.complete(req)
    key = cache_key("openai", "test-model", req)
    assert info.value.key == key and key in str(info.value)
    assert server.count == 0


def test_errors_are_not_cached(server: ChatServer, tmp_path: Path) -> None:
    server.push(status(400), reply("ok"))
    backend = make_backend("openai:test-model", base_url=server.url, cache_dir=tmp_path)
    with pytest.raises(LLMRequestRejectedError):
        backend.complete(_request())
    assert backend.complete(_request()).content == "ok"


def test_call_budget_refuses_before_calling() -> None:
    inner = Counting()
    backend = BudgetedBackend(inner, max_calls=2)
    backend.complete(_request("a"))
    backend.complete(_request("b"))
    with pytest.raises(LLMBudgetExceededError, match="2 of 2 calls"):
        backend.complete(_request("c"))
    assert inner.calls == 2
    assert backend.usage()["calls"] == 2 and backend.usage()["total_tokens"] == 40


def test_token_budget_refuses_once_spent() -> None:
    inner = Counting(tokens=30)
    backend = BudgetedBackend(inner, max_tokens_total=100)
    backend.complete(_request("a"))  # 60 tokens
    backend.complete(_request("b"))  # 120 tokens: the last call may overshoot
    with pytest.raises(LLMBudgetExceededError, match="tokens"):
        backend.complete(_request("c"))
    assert inner.calls == 2


def test_budget_state_dict_round_trip() -> None:
    backend = BudgetedBackend(Counting(), max_calls=3)
    backend.complete(_request())
    backend.complete(_request())
    resumed = BudgetedBackend(Counting(), max_calls=3)
    resumed.load_state_dict(json.loads(json.dumps(backend.state_dict())))
    assert resumed.state_dict() == backend.state_dict()
    resumed.complete(_request())
    with pytest.raises(LLMBudgetExceededError):
        resumed.complete(_request())


def test_cache_hits_do_not_spend_the_budget(tmp_path: Path) -> None:
    script = tmp_path / "s.jsonl"
    script.write_text('{"content": "one"}\n{"content": "two"}\n')
    backend = make_backend(f"script:{script}", cache_dir=tmp_path / "c", max_calls=1)
    assert backend.complete(_request("q")).content == "one"
    assert backend.complete(_request("q")).cached  # replay: free
    with pytest.raises(LLMBudgetExceededError):
        backend.complete(_request("other"))


def _offline_context() -> dict[str, object]:
    return {
        "task": "halfcheetah",
        "features": [{"name": n, "units": "", "doc": ""} for n in ("x_velocity", "pitch", "pitch_rate")],
        "action_dim": 6,
    }


def test_audit_log_records_every_exchange_and_parse_result(tmp_path: Path) -> None:
    backend = make_backend("offline", audit_dir=tmp_path, cache_dir=tmp_path / "cache")
    assert isinstance(backend, AuditedBackend)
    req = LLMRequest(
        messages=[{"role": "user", "content": "card"}], purpose="lsfs", context=_offline_context()
    )
    first = backend.complete(req)
    backend.record_parse_result(first, {"ok": True, "factors": 4})
    second = backend.complete(req)
    assert second.cached
    bad = LLMRequest(messages=[{"role": "user", "content": "no context"}], purpose="srr")
    with pytest.raises(LLMRequestRejectedError):
        backend.complete(bad)
    records = AuditLog(tmp_path).read()
    assert [r["cached"] for r in records] == [False, True, False]
    assert records[0]["parse_result"] == {"ok": True, "factors": 4}
    assert records[0]["reply"] == first.content and records[0]["messages"] == req.messages
    assert records[0]["purpose"] == "lsfs" and records[0]["model"] == "rule-based-engineer-v2"
    assert records[2]["error"]["type"] == "LLMRequestRejectedError" and records[2]["reply"] is None
    for field in ("timestamp", "backend", "latency_s", "usage", "attempts", "context"):
        assert field in records[0]
    raw_lines = (tmp_path / "llm" / "exchanges.jsonl").read_text().splitlines()
    assert len(raw_lines) == 4
    assert all(json.loads(line)["engineer"] == OFFLINE_ENGINEER_LABEL for line in raw_lines)


def test_audited_script_names_itself_not_an_llm(tmp_path: Path) -> None:
    script = tmp_path / "s.jsonl"
    script.write_text('{"content": "x"}\n')
    backend = AuditedBackend(ScriptBackend(script), AuditLog(tmp_path))
    backend.complete(_request())
    (record,) = AuditLog(tmp_path).read()
    assert record["engineer"] == "scripted replies from s.jsonl (not an LLM)"


def test_offline_engineer_through_cache_is_reproducible(tmp_path: Path) -> None:
    req = LLMRequest(
        messages=[{"role": "user", "content": "card"}], purpose="lsfs", context=_offline_context()
    )
    direct = OfflineEngineer().complete(req).content
    cached = make_backend("offline", cache_dir=tmp_path)
    assert cached.complete(req).content == direct
    assert cached.complete(req).content == direct
