"""``mira llm export``: a run's exchanges as a script or a response cache that replays them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mira.cli import main
from mira.engineer.backends import make_backend
from mira.errors import UsageError
from mira.llm.audit import AuditLog
from mira.llm.base import LLMCacheMissError, LLMReply, LLMRequest, LLMUnavailableError, TokenUsage
from mira.llm.cache import CachedBackend
from mira.llm.export import export_run, prompt_sha256, read_exchanges
from mira.llm.script import ScriptBackend


def _request(text: str, purpose: str = "srr") -> LLMRequest:
    return LLMRequest(messages=[{"role": "system", "content": "you write rewards"},
                                {"role": "user", "content": text}], purpose=purpose, seed=3)  # type: ignore[arg-type]


def _reply(content: str) -> LLMReply:
    return LLMReply(content=content, backend="openai", model="gpt-test", usage=TokenUsage(11, 7),
                    latency_s=0.5, finish_reason="stop")


class _Unreachable:
    """The endpoint of a replay: never to be called."""

    name = "openai"
    model = "gpt-test"

    def complete(self, request: LLMRequest) -> LLMReply:
        raise AssertionError(f"a replay reached the endpoint ({request.purpose})")


def _run(tmp_path: Path) -> tuple[Path, list[LLMRequest]]:
    """A run directory whose audit log holds an LSFS answer with a parse result, a failed SRR call,
    and an SRR answer."""
    run = tmp_path / "run"
    log = AuditLog(run)
    first, failed, second = _request("write a program", "lsfs"), _request("edit it"), _request("edit it again")
    ex1 = log.record_exchange(first, backend="openai", model="gpt-test", reply=_reply("PROGRAM ü"))
    log.record_parse_result(ex1, {"ok": True, "factors": 3})
    log.record_exchange(failed, backend="openai", model="gpt-test",
                        error=LLMUnavailableError("down", attempts=5), latency_s=2.0)
    log.record_exchange(second, backend="openai", model="gpt-test", reply=_reply("EDITS"))
    return run, [first, failed, second]


def test_script_export_replays_the_replies_in_order(tmp_path: Path) -> None:
    run, (first, _, second) = _run(tmp_path)
    result = export_run(run)
    out = run / "llm" / "script.jsonl"
    assert result.out == out and dict(result.written) == {"lsfs": 1, "srr": 1} and dict(result.skipped) == {"srr": 1}
    lines = [json.loads(line) for line in out.read_text(encoding="utf-8").splitlines()]
    assert [line["content"] for line in lines] == ["PROGRAM ü", "EDITS"]
    assert lines[0]["parse_result"] == {"ok": True, "factors": 3} and lines[1]["parse_result"] is None
    assert (lines[0]["purpose"], lines[0]["model"], lines[0]["engineer"]) == ("lsfs", "gpt-test",
                                                                                "LLM gpt-test via openai")
    assert lines[0]["prompt_sha256"] == prompt_sha256(first.messages) != lines[1]["prompt_sha256"]
    assert lines[0]["usage"] == {"prompt_tokens": 11, "completion_tokens": 7}
    script = ScriptBackend(out)  # the extra keys are read past
    replies = [script.complete(first), script.complete(second)]
    assert [r.content for r in replies] == ["PROGRAM ü", "EDITS"] and script.position == len(script)
    assert replies[0].usage == TokenUsage(11, 7)
    summary = result.summary()
    assert "wrote 2 exchanges (lsfs 1, srr 1)" in summary and "skipped 1 without a reply (srr 1)" in summary
    assert f"--llm script:{out}" in summary and "1 LLMUnavailableError" in summary


def test_a_repeated_request_gets_no_script_line(tmp_path: Path) -> None:
    """A request asked again is answered by the replay's cache, as it was by the run's: no line for it."""
    run = tmp_path / "run"
    log = AuditLog(run)
    ask, other = _request("same question"), _request("another")
    log.record_exchange(ask, backend="openai", model="gpt-test", reply=_reply("A"))
    log.record_exchange(ask, backend="openai", model="gpt-test", reply=_reply("A"))
    log.record_exchange(other, backend="openai", model="gpt-test", reply=_reply("B"))
    script = tmp_path / "replies.jsonl"
    result = export_run(run, script)
    assert result.repeats == 1 and "left to the replay's cache" in result.summary()
    replay = make_backend(f"script:{script}", cache_dir=tmp_path / "replay-cache")
    assert [replay.complete(r).content for r in (ask, ask, other)] == ["A", "A", "B"]


def test_cache_export_answers_the_original_requests_offline(tmp_path: Path) -> None:
    run, (first, failed, second) = _run(tmp_path)
    cache_dir = tmp_path / "shared-cache"
    result = export_run(run, cache_dir, "cache")
    assert sum(result.written.values()) == 2 and result.specs == ["openai:gpt-test"]
    assert "--llm openai:gpt-test --llm-cache" in result.summary() and "--llm-offline-only" in result.summary()
    replay = CachedBackend(_Unreachable(), cache_dir, offline_only=True)
    for request, content in ((first, "PROGRAM ü"), (second, "EDITS")):
        reply = replay.complete(request)
        assert (reply.content, reply.cached, reply.usage, reply.finish_reason) == (content, True, TokenUsage(11, 7),
                                                                                   "stop")
    with pytest.raises(LLMCacheMissError):  # the failed call was not invented an answer
        replay.complete(failed)


def test_the_cli_exports_and_prints_a_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run, _ = _run(tmp_path)
    out = tmp_path / "x" / "script.jsonl"
    assert main(["llm", "export", str(run), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "wrote 2 exchanges" in printed and str(out) in printed and len(ScriptBackend(out)) == 2
    assert main(["llm", "export", str(run), "--format", "cache", "--out", str(tmp_path / "c")]) == 0
    assert "--llm openai:gpt-test" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        (lambda run: None, "no such run directory"),
        (lambda run: run.mkdir(), "no audit log"),
        (lambda run: (run / "llm").mkdir(parents=True) or (run / "llm" / "exchanges.jsonl").write_text(
            '{"kind": "exchange"\n{}\n'), "line 1: not valid JSON"),
    ],
)
def test_the_cli_names_the_path_of_a_bad_run(tmp_path: Path, capsys: pytest.CaptureFixture[str], setup: object,
                                             message: str) -> None:
    run = tmp_path / "run"
    setup(run)  # type: ignore[operator]
    assert main(["llm", "export", str(run)]) == 2
    err = capsys.readouterr().err
    assert message in err and str(run) in err and "\n" not in err.strip()


def test_a_malformed_line_is_named_and_nothing_is_written(tmp_path: Path) -> None:
    run, _ = _run(tmp_path)
    log = run / "llm" / "exchanges.jsonl"
    lines = log.read_text(encoding="utf-8").splitlines()
    log.write_text("\n".join([*lines[:2], "not json", *lines[2:]]) + "\n", encoding="utf-8")
    with pytest.raises(UsageError, match=r"exchanges\.jsonl, line 3: not valid JSON"):
        export_run(run, tmp_path / "out.jsonl")
    with pytest.raises(UsageError, match="line 3"):
        export_run(run, tmp_path / "cache", "cache")
    assert not (tmp_path / "out.jsonl").exists() and not (tmp_path / "cache").exists()
    log.write_text(lines[0] + '\n{"kind": "exchange", "id": "x", "backend": "openai", "model": "m"}\n')
    with pytest.raises(UsageError, match=r"line 2: exchange record without 'messages'"):
        export_run(run)


def test_a_torn_last_line_is_dropped_as_the_run_drops_it(tmp_path: Path) -> None:
    run, _ = _run(tmp_path)
    log = run / "llm" / "exchanges.jsonl"
    with log.open("a", encoding="utf-8") as handle:
        handle.write('{"kind": "exchange", "id": "tor')
    exchanges, torn = read_exchanges(run)
    assert len(exchanges) == 3 and torn == 5
    assert "ignored the torn last line 5" in export_run(run).summary()


def test_refusals(tmp_path: Path) -> None:
    run, _ = _run(tmp_path)
    with pytest.raises(UsageError, match="needs --out DIR"):
        export_run(run, None, "cache")
    with pytest.raises(UsageError, match="is a directory"):
        export_run(run, tmp_path, "script")
    with pytest.raises(UsageError, match="audit log itself"):
        export_run(run, run / "llm" / "exchanges.jsonl")
    (tmp_path / "file").write_text("")
    with pytest.raises(UsageError, match="is a file"):
        export_run(run, tmp_path / "file", "cache")
    empty = tmp_path / "failed-run"
    AuditLog(empty).record_exchange(_request("q"), backend="openai", model="m", error=LLMUnavailableError("down"))
    with pytest.raises(UsageError, match=r"no exchange got a reply \(1 recorded\)"):
        export_run(empty)
