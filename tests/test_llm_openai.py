"""The openai:MODEL backend against a real HTTP server on 127.0.0.1 (no key, no internet)."""

from __future__ import annotations

import random
import time
from collections.abc import Iterator

import openai
import pytest

from chat_server import ChatServer, hang, raw, reply, status
from mira.errors import UsageError
from mira.llm.base import LLMBadReplyError, LLMRequest, LLMRequestRejectedError, LLMUnavailableError
from mira.llm.openai_backend import DUMMY_LOCAL_KEY, OpenAIBackend, parse_retry_after


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[ChatServer]:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    monkeypatch.delenv("MIRA_BASE_URL", raising=False)
    with ChatServer() as srv:
        yield srv


def _request(**kw: object) -> LLMRequest:
    return LLMRequest(
        messages=[
            {"role": "system", "content": "You are a reward engineer."},
            {"role": "user", "content": "hi"},
        ],
        purpose="lsfs",
        **kw,  # type: ignore[arg-type]
    )


def _backend(srv: ChatServer, sleeps: list[float], **kw: object) -> OpenAIBackend:
    kw.setdefault("max_retries", 3)
    kw.setdefault("timeout_s", 5.0)
    return OpenAIBackend(
        "test-model",
        base_url=srv.url,
        sleep=sleeps.append,
        rng=random.Random(0),
        **kw,  # type: ignore[arg-type]
    )


def test_good_reply_sends_temperature_zero_and_records_usage(server: ChatServer) -> None:
    server.push(reply('{"task": "x"}', prompt_tokens=21, completion_tokens=5))
    sleeps: list[float] = []
    out = _backend(server, sleeps).complete(_request(seed=3, max_tokens=100))
    assert out.content == '{"task": "x"}'
    assert (out.backend, out.model, out.cached, out.attempts) == ("openai", "test-model", False, 1)
    assert (out.usage.prompt_tokens, out.usage.completion_tokens) == (21, 5)
    assert out.finish_reason == "stop" and out.latency_s >= 0 and sleeps == []
    sent = server.requests[0]
    assert sent["path"] == "/v1/chat/completions"
    assert sent["json"]["temperature"] == 0.0
    assert sent["json"]["seed"] == 3 and sent["json"]["max_tokens"] == 100
    assert sent["json"]["messages"][1] == {"role": "user", "content": "hi"}
    assert sent["headers"]["authorization"] == f"Bearer {DUMMY_LOCAL_KEY}"


def test_prose_and_code_fences_are_returned_verbatim(server: ChatServer) -> None:
    text = 'Here is the program:\n```json\n{"candidates": []}\n```\nHope this helps.'
    server.push(reply(text))
    assert _backend(server, []).complete(_request()).content == text


def test_429_then_success_is_retried_honouring_retry_after(server: ChatServer) -> None:
    server.push(status(429, headers={"Retry-After": "3"}), reply("ok"))
    sleeps: list[float] = []
    out = _backend(server, sleeps).complete(_request())
    assert out.content == "ok" and out.attempts == 2
    assert server.count == 2
    assert sleeps == [3.0]


def test_429_without_retry_after_uses_jittered_backoff(server: ChatServer) -> None:
    server.push(status(429), status(503), reply("ok"))
    sleeps: list[float] = []
    out = _backend(server, sleeps, backoff_base_s=1.0).complete(_request())
    assert out.attempts == 3 and len(sleeps) == 2
    assert 0.5 <= sleeps[0] <= 1.0 and 1.0 <= sleeps[1] <= 2.0


def test_repeated_500s_raise_unavailable_after_the_retry_budget(server: ChatServer) -> None:
    retries = 3
    server.push(*[status(500) for _ in range(retries + 1)])
    sleeps: list[float] = []
    backend = _backend(server, sleeps, max_retries=retries, backoff_base_s=0.5, backoff_max_s=1.5)
    with pytest.raises(LLMUnavailableError) as info:
        backend.complete(_request())
    assert server.count == 1 + retries
    assert info.value.attempts == 1 + retries
    assert isinstance(info.value.cause, openai.InternalServerError)
    assert "HTTP 500" in str(info.value)
    assert len(sleeps) == retries
    for i, delay in enumerate(sleeps):  # capped exponential backoff with equal jitter
        ceiling = min(1.5, 0.5 * 2**i)
        assert ceiling / 2 <= delay <= ceiling


def test_hung_socket_times_out_within_bounded_time(server: ChatServer) -> None:
    server.push(hang(30), hang(30))
    sleeps: list[float] = []
    backend = _backend(server, sleeps, timeout_s=0.4, max_retries=1)
    started = time.monotonic()
    with pytest.raises(LLMUnavailableError) as info:
        backend.complete(_request())
    assert time.monotonic() - started < 10
    assert isinstance(info.value.cause, openai.APITimeoutError)
    assert server.count == 2 and len(sleeps) == 1


def test_non_retryable_400_is_one_request_and_rejected(server: ChatServer) -> None:
    server.push(status(400, message="bad model"), reply("never sent"))
    sleeps: list[float] = []
    with pytest.raises(LLMRequestRejectedError) as info:
        _backend(server, sleeps).complete(_request())
    assert info.value.status_code == 400 and "bad model" in str(info.value)
    assert server.count == 1 and sleeps == []


def test_401_is_not_retried(server: ChatServer) -> None:
    server.push(status(401))
    with pytest.raises(LLMRequestRejectedError):
        _backend(server, []).complete(_request())
    assert server.count == 1


def test_empty_or_blank_reply_is_an_error(server: ChatServer) -> None:
    server.push(reply("   \n"))
    with pytest.raises(LLMBadReplyError):
        _backend(server, []).complete(_request())


def test_no_choices_is_an_error(server: ChatServer) -> None:
    server.push(raw(b'{"id": "x", "object": "chat.completion", "created": 0, "model": "m", "choices": []}'))
    with pytest.raises(LLMBadReplyError):
        _backend(server, []).complete(_request())


def test_connection_refused_is_unavailable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    with ChatServer() as srv:
        url = srv.url  # a port that is closed once the server is gone
    sleeps: list[float] = []
    backend = OpenAIBackend("m", base_url=url, max_retries=2, timeout_s=2, sleep=sleeps.append)
    with pytest.raises(LLMUnavailableError) as info:
        backend.complete(_request())
    assert isinstance(info.value.cause, openai.APIConnectionError) and len(sleeps) == 2


def test_base_url_and_key_from_environment(server: ChatServer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MIRA_BASE_URL", server.url)
    monkeypatch.setenv("MY_KEY", "sk-test-123")
    server.push(reply("ok"))
    backend = OpenAIBackend("m", api_key_env="MY_KEY")
    assert backend.base_url == server.url
    backend.complete(_request())
    assert server.requests[0]["headers"]["authorization"] == "Bearer sk-test-123"


def test_missing_key_for_remote_endpoint_is_a_usage_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NO_SUCH_KEY_VAR", raising=False)
    with pytest.raises(UsageError, match="NO_SUCH_KEY_VAR"):
        OpenAIBackend("m", base_url="https://api.example.com/v1", api_key_env="NO_SUCH_KEY_VAR")


def test_retry_after_parsing() -> None:
    assert parse_retry_after({"retry-after": "2.5"}) == 2.5
    assert parse_retry_after({"retry-after-ms": "1500"}) == 1.5
    assert parse_retry_after({"retry-after": "Wed, 21 Oct 2015 07:28:10 GMT"}, now=1445412480.0) == 10.0
    assert parse_retry_after({"retry-after": "soon"}) is None
    assert parse_retry_after({}) is None


def test_a_body_that_is_not_json_is_a_typed_error() -> None:
    from chat_server import ChatServer, raw
    from mira.llm.base import LLMBadReplyError, LLMRequest
    from mira.llm.openai_backend import OpenAIBackend

    with ChatServer() as server:
        server.push(raw(b"this is not JSON at all"))
        backend = OpenAIBackend("m", base_url=server.url, api_key_env="MIRA_TEST_NO_SUCH_KEY", max_retries=0,
                                timeout_s=5)
        with pytest.raises(LLMBadReplyError, match="not JSON"):
            backend.complete(LLMRequest(messages=[{"role": "user", "content": "hi"}]))
