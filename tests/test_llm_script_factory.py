"""The script:FILE backend and the --llm spec factory."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mira.engineer.backends import backend_state_dict, find_layer, load_backend_state_dict, make_backend
from mira.engineer.offline import OfflineEngineer
from mira.errors import UsageError
from mira.llm.audit import AuditedBackend
from mira.llm.base import LLMRequest, ScriptExhaustedError, ScriptFormatError
from mira.llm.budget import BudgetedBackend
from mira.llm.cache import CachedBackend
from mira.llm.openai_backend import OpenAIBackend
from mira.llm.script import ScriptBackend


def _request(text: str = "q") -> LLMRequest:
    return LLMRequest(messages=[{"role": "user", "content": text}], purpose="srr")


def _script(tmp_path: Path, *lines: str) -> Path:
    path = tmp_path / "replies.jsonl"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_script_answers_in_order_then_is_exhausted(tmp_path: Path) -> None:
    path = _script(tmp_path, '{"content": "first"}', "", '{"content": "second"}')
    backend = ScriptBackend(path)
    assert len(backend) == 2
    assert backend.complete(_request()).content == "first"
    out = backend.complete(_request())
    assert (out.content, out.backend, out.model) == ("second", "script", "replies.jsonl")
    with pytest.raises(ScriptExhaustedError, match=r"holds 2 replies and call 3"):
        backend.complete(_request())


def test_script_malformed_line_names_the_line(tmp_path: Path) -> None:
    path = _script(tmp_path, '{"content": "ok"}', "", '{"content": ')
    with pytest.raises(ScriptFormatError, match="line 3"):
        ScriptBackend(path)
    with pytest.raises(ScriptFormatError, match="line 1"):
        ScriptBackend(_script(tmp_path, '{"text": "no content key"}'))
    with pytest.raises(ScriptFormatError, match=r"line 2.*empty"):
        ScriptBackend(_script(tmp_path, '{"content": "a"}', '{"content": "  "}'))
    with pytest.raises(ScriptFormatError, match=r"line 1.*string"):
        ScriptBackend(_script(tmp_path, '{"content": 5}'))


def test_script_missing_file_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="cannot read"):
        make_backend(f"script:{tmp_path / 'absent.jsonl'}")


def test_script_usage_and_position_checkpoint(tmp_path: Path) -> None:
    path = _script(
        tmp_path,
        '{"content": "a", "usage": {"prompt_tokens": 5, "completion_tokens": 2}}',
        '{"content": "b"}',
        '{"content": "c"}',
    )
    backend = ScriptBackend(path)
    assert backend.complete(_request()).usage.total_tokens == 7
    state = json.loads(json.dumps(backend.state_dict()))
    resumed = ScriptBackend(path)
    resumed.load_state_dict(state)
    assert resumed.complete(_request()).content == "b" and resumed.position == 2
    path.write_text('{"content": "changed"}\n')
    with pytest.raises(ScriptFormatError, match="changed"):
        ScriptBackend(path).load_state_dict(state)


@pytest.mark.parametrize(
    "spec", ["", "gpt-4", "openai", "openai:", "script:", "offline:x", "Offline", "deepseek:chat"]
)
def test_bad_spec_is_a_one_line_usage_error(spec: str) -> None:
    with pytest.raises(UsageError) as info:
        make_backend(spec)
    assert "\n" not in str(info.value)


def test_layering(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    plain = make_backend("offline")
    assert isinstance(plain, OfflineEngineer)
    full = make_backend(
        "openai:llama3",
        base_url="http://127.0.0.1:9/v1",
        cache_dir=tmp_path / "cache",
        audit_dir=tmp_path / "run",
        max_calls=5,
        timeout_s=3,
        max_retries=1,
    )
    assert isinstance(full, AuditedBackend)
    assert isinstance(full.inner, CachedBackend)
    assert isinstance(full.inner.inner, BudgetedBackend)
    openai_layer = find_layer(full, OpenAIBackend)
    assert openai_layer is not None and openai_layer.max_retries == 1 and openai_layer.timeout_s == 3
    assert (full.name, full.model) == ("openai", "llama3")
    with pytest.raises(UsageError, match="cache directory"):
        make_backend("offline", offline_only=True)


def test_backend_state_dict_covers_budget_and_script(tmp_path: Path) -> None:
    path = _script(tmp_path, '{"content": "a"}', '{"content": "b"}')
    backend = make_backend(f"script:{path}", max_calls=10, cache_dir=tmp_path / "c")
    backend.complete(_request("1"))
    state = backend_state_dict(backend)
    assert state["ScriptBackend"]["position"] == 1 and state["BudgetedBackend"]["calls"] == 1
    resumed = make_backend(f"script:{path}", max_calls=10, cache_dir=tmp_path / "c2")
    load_backend_state_dict(resumed, json.loads(json.dumps(state)))
    assert resumed.complete(_request("2")).content == "b"
    budget = find_layer(resumed, BudgetedBackend)
    assert budget is not None and budget.calls == 2


def test_request_validation() -> None:
    with pytest.raises(ValueError, match="purpose"):
        LLMRequest(messages=[{"role": "user", "content": "x"}], purpose="chat")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="role"):
        LLMRequest(messages=[{"role": "robot", "content": "x"}])
    with pytest.raises(ValueError):
        LLMRequest(messages=[])
