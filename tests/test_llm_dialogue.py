"""A refused reply goes back to the model with its errors; what models write is read; prompts say what is true."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mira.engineer.backends import make_backend
from mira.engineer.lsfs import SynthesisError, synthesize_program
from mira.engineer.lsfs_prompt import build_lsfs_messages, parse_program_reply
from mira.engineer.srr_candidates import parse_candidates
from mira.engineer.srr_prompt import Evidence, build_srr_request
from mira.factors import ProgramParseError, example_program
from mira.factors.sandbox import collect_states
from mira.llm.audit import AuditLog
from mira.srr.config import SRRConfig
from mira.srr.reframe import Reframer
from mira.tasks import load_task

CARD = load_task("halfcheetah")


def _factor(name: str, code: str, ftype: str = "PHI") -> dict[str, str]:
    return {"name": name, "type": ftype, "code": code, "doc": "d", "units": "1", "range_hint": "[-20, 20]"}


def _program_reply(feature: str) -> str:
    return json.dumps({"factors": [
        _factor("r_progress", f"def r_progress(s):\n    return s.{feature}\n"),
        _factor("r_effort", "def r_effort(s, a):\n    return -np.sum(np.square(a), axis=-1)\n", "AUX"),
    ]})


def _script(tmp_path: Path, replies: list[str]) -> str:
    path = tmp_path / "replies.jsonl"
    path.write_text("".join(json.dumps({"content": r}) + "\n" for r in replies))
    return f"script:{path}"


def test_lsfs_reply_with_unknown_feature_is_sent_back_and_the_corrected_one_admitted(tmp_path: Path) -> None:
    backend = make_backend(_script(tmp_path, [_program_reply("forward_speed"), _program_reply("x_velocity")]),
                           audit_dir=tmp_path)
    made = synthesize_program(CARD, backend, 6, followups=2)
    assert len(made.attempts) == 2 and made.retries == 1
    assert "s.x_velocity" in made.program.factor("r_progress").code
    exchanges = AuditLog(tmp_path).read()
    assert [e["parse_result"]["admitted"] for e in exchanges] == [False, True]
    second = exchanges[1]["messages"]
    # The follow-up is a turn of the same conversation: the refused reply, then its errors with the line.
    assert [m["role"] for m in second] == ["system", "user", "assistant", "user"]
    assert second[2]["content"] == _program_reply("forward_speed")
    assert "forward_speed" in second[3]["content"] and "return s.forward_speed" in second[3]["content"]
    assert "forward_speed" in " ".join(exchanges[0]["parse_result"]["errors"])


def test_lsfs_gives_up_after_the_follow_ups_with_every_attempt(tmp_path: Path) -> None:
    backend = make_backend(_script(tmp_path, [_program_reply("nope")] * 3), audit_dir=tmp_path)
    with pytest.raises(SynthesisError) as info:
        synthesize_program(CARD, backend, 6, followups=2)
    assert len(info.value.attempts) == 3 and all(a.errors for a in info.value.attempts)
    assert "3 attempts" in str(info.value)


def test_offline_engineer_gets_no_follow_up() -> None:
    from mira.engineer.dialogue import reads_followups

    assert not reads_followups(make_backend("offline"))


def test_literal_newlines_and_tabs_in_code_strings_parse() -> None:
    reply = ('{"factors": [{"name": "r_v", "type": "PHI", "code": "def r_v(s):\n\treturn s.x_velocity\n", '
             '"doc": "d", "units": "m/s", "range_hint": "[-15, 15]"}]}')
    program = parse_program_reply(reply, CARD)
    assert program.factor("r_v").code == "def r_v(s):\n\treturn s.x_velocity\n"
    cand = {"edits": [{"operator": "Refactor", "targets": ["r_vel"], "params": {}}],
            "updated_factors": [_factor("r_vel", "def r_vel(s):\n    return 2.0 * s.x_velocity\n")]}
    raw = json.dumps({"candidates": [cand]}).replace("\\n", "\n")
    assert "\n    return" in raw
    (parsed,) = parse_candidates("Sure:\n" + raw + "\nHope this helps.", example_program("halfcheetah", 0), 2)
    assert parsed.program is not None and "2.0 * s.x_velocity" in parsed.program.factor("r_vel").code


def test_a_json_error_inside_a_fence_is_located_in_the_reply() -> None:
    reply = 'Here is the program.\n\n```json\n{"factors": [\n  {"name": "r_v",, "type": "PHI"}\n]}\n```\n'
    with pytest.raises(ProgramParseError) as info:
        parse_program_reply(reply, CARD)
    text = str(info.value)
    assert "line 5" in text and '"r_v",,' in text  # the reply's line, not the fence's first


def test_lsfs_example_uses_the_task_own_fields_and_says_how_factors_are_used() -> None:
    hopper = load_task("hopper")
    user = build_lsfs_messages(hopper, 3)[1]["content"]
    assert "s.pitch" not in user and f"s.{hopper.features[0].name}" in user
    assert "fits a per-step reward" in user and "potential-based shaping signal" not in user


def _structural_evidence() -> Evidence:
    d = {"peg": 0.1, "tpd": 0.0, "pvc": -0.2, "fap": 0.1, "rpe": 0.3}
    return Evidence(step=13000, d=d, d_raw=d, score=None, threshold=None, gradient=dict.fromkeys(d, 0.0),
                    contributors=[], recent_return=-1.0, baseline_return=-1.0, stagnation_band=None, attention={},
                    cause="structural",
                    return_attribution={"episodes": 12, "program_cv_r2": -0.4, "feature_gains": [
                        {"feature": "x_velocity", "form": "value", "cv_r2": 0.99, "gain": 1.39, "share": 0.99,
                         "range": [-3.0, 3.0]}]})


def test_srr_prompt_names_the_structural_check_and_leaves_out_what_was_not_measured() -> None:
    from mira.srr.hypotheses import rule_hypotheses

    ev = _structural_evidence()
    hyps = rule_hypotheses({**ev.d, "tpd": 3.0, "peg": -3.0}, True)
    assert hyps  # the monitor's rules would say something; for a structural trigger it is not said
    text = build_srr_request(CARD, example_program("halfcheetah", 0), ev, hyps, 2,
                             ("Scale", "Sat", "Gate", "Refactor", "Add", "Prune"), 6).messages[1]["content"]
    assert "TRIGGER: the structural check" in text
    for absent in ("anomaly_score", "top_contributors", "direction_to_healthy", "failure_hypotheses"):
        assert absent not in text, absent
    assert '{"alpha": number}' in text and '{"lo": number, "hi": number}' in text  # operators' params
    assert "x_velocity: R² 0.990" in text


@pytest.fixture(scope="module")
def states() -> tuple[np.ndarray, np.ndarray]:
    return collect_states(CARD, 300, seed=5)


def _candidate_reply(feature: str) -> str:
    cand = {"edits": [{"operator": "Add", "targets": ["r_progress"], "params": {"type": "PHI"},
                       "justification": "the returns follow forward velocity"}],
            "updated_factors": [_factor("r_progress", f"def r_progress(s):\n    return s.{feature}\n")]}
    return json.dumps({"candidates": [cand]})


def test_srr_candidate_with_unknown_feature_is_sent_back_and_the_corrected_one_installed(
        tmp_path: Path, states: tuple[np.ndarray, np.ndarray]) -> None:
    obs, actions = states
    backend = make_backend(_script(tmp_path, [_candidate_reply("forward_speed"), _candidate_reply("x_velocity")]),
                           audit_dir=tmp_path)
    values = CARD.feature_values(obs)["x_velocity"]
    reframer = Reframer(SRRConfig(), CARD, backend, action_dim=6, followups=1, permutations=100)

    def proxy(program, s):  # type: ignore[no-untyped-def]
        return CARD.feature_values(s)["x_velocity"]

    decision = reframer.reframe(tmp_path / "iv", example_program("halfcheetah", 0), _structural_evidence(), obs,
                                values, obs, actions, proxy, seed=0)
    assert decision.accepted and "s.x_velocity" in decision.program.factor("r_progress").code
    exchanges = AuditLog(tmp_path).read()
    assert len(exchanges) == 2 and "forward_speed" in exchanges[1]["messages"][-1]["content"]
    assert exchanges[0]["parse_result"]["admitted"] is False and exchanges[1]["parse_result"]["admitted"] is True
    attempts = json.loads((tmp_path / "iv" / "attempts.json").read_text())
    assert [a["admitted"] for a in attempts] == [False, True]
    assert (tmp_path / "iv" / "response-1.txt").read_text() == _candidate_reply("forward_speed")


def test_the_next_srr_prompt_lists_the_candidates_refused_last_time(
        tmp_path: Path, states: tuple[np.ndarray, np.ndarray]) -> None:
    obs, actions = states
    backend = make_backend(_script(tmp_path, [_candidate_reply("forward_speed")] * 2), audit_dir=tmp_path)
    reframer = Reframer(SRRConfig(), CARD, backend, action_dim=6, followups=0, permutations=100)
    values = CARD.feature_values(obs)["x_velocity"]

    def proxy(program, s):  # type: ignore[no-untyped-def]
        return CARD.feature_values(s)["x_velocity"]

    program = example_program("halfcheetah", 0)
    first = reframer.reframe(tmp_path / "a", program, _structural_evidence(), obs, values, obs, actions, proxy, seed=0)
    assert not first.accepted and reframer.refused and "forward_speed" in reframer.refused[0]["reason"]
    reframer.reframe(tmp_path / "b", program, _structural_evidence(), obs, values, obs, actions, proxy, seed=0)
    second = AuditLog(tmp_path).read()[1]["messages"][1]["content"]
    assert "PREVIOUSLY_REFUSED" in second and "forward_speed" in second and "[Add on r_progress]" in second


def test_a_program_file_is_credited_to_its_file_and_an_llm_program_to_the_llm(tmp_path: Path) -> None:
    from mira.config import TrainConfig
    from mira.explain import _program_origin
    from mira.factors.program import save_program
    from mira.methods.hars import initial_program

    path = tmp_path / "mine.json"
    save_program(example_program("halfcheetah", 0), path)
    run = tmp_path / "run"
    initial_program(TrainConfig(task="halfcheetah", program=str(path)), CARD, run)
    origin = json.loads((run / "programs" / "origin.json").read_text())
    assert origin["written_by"] == "file" and origin["file"] == str(path)
    llm_cfg = {"llm": {"backend": "openai:some-model"}, "program": str(path)}
    assert _program_origin(run, llm_cfg) == f"was read from {path}"

    llm_run = tmp_path / "llm-run"
    cfg = TrainConfig(task="halfcheetah")
    cfg.llm.backend = _script(tmp_path, [_program_reply("forward_speed"), _program_reply("x_velocity")])
    initial_program(cfg, CARD, llm_run)
    assert _program_origin(llm_run, {}) == (f"was written by {cfg.llm.backend}, admitted on attempt 2 (the earlier "
                                            "replies were sent back with their errors)")


def test_every_refused_lsfs_reply_falls_back_to_the_offline_engineer_and_says_so(tmp_path: Path) -> None:
    from mira.config import TrainConfig
    from mira.explain import _program_origin
    from mira.methods.hars import initial_program

    cfg = TrainConfig(task="halfcheetah")
    cfg.llm.backend = _script(tmp_path, [_program_reply("nope")] * 3)
    program = initial_program(cfg, CARD, tmp_path / "run")
    assert program.factors  # the offline engineer's program
    origin = json.loads((tmp_path / "run" / "programs" / "origin.json").read_text())
    assert origin["written_by"] == "offline" and origin["fallback_from"] == cfg.llm.backend
    assert len(origin["attempts"]) == 3
    assert "because every reply of script:" in _program_origin(tmp_path / "run", {})
    engineers = [e["engineer"] for e in AuditLog(tmp_path / "run").read()]
    assert len(engineers) == 4 and "not an LLM" in engineers[-1]


def test_a_prune_only_candidate_is_judged_not_lost(tmp_path: Path, states: tuple[np.ndarray, np.ndarray]) -> None:
    """A candidate that only removes a factor changes no code the sandbox has not seen: it goes on to the
    efficacy test (it once made the admission step raise, and the whole reply was lost)."""
    obs, actions = states
    prune = {"candidates": [{"edits": [{"operator": "Prune", "targets": ["r_stable"], "params": {},
                                        "justification": "inert"}], "updated_factors": []}]}
    backend = make_backend(_script(tmp_path, [json.dumps(prune)]), audit_dir=tmp_path)
    reframer = Reframer(SRRConfig(), CARD, backend, action_dim=6, followups=0, permutations=100)
    values = CARD.feature_values(obs)["x_velocity"]

    def proxy(program, s):  # type: ignore[no-untyped-def]
        return CARD.feature_values(s)["x_velocity"]

    decision = reframer.reframe(tmp_path / "iv", example_program("halfcheetah", 0), _structural_evidence(), obs,
                                values, obs, actions, proxy, seed=0)
    assert not decision.failed
    (record,) = json.loads((tmp_path / "iv" / "candidates.json").read_text())
    assert "efficacy" in record["verdicts"] and "r_stable" not in [f["name"] for f in record["program"]["factors"]]


def test_a_structural_intervention_records_no_rule_hypotheses(tmp_path: Path,
                                                               states: tuple[np.ndarray, np.ndarray]) -> None:
    obs, actions = states
    backend = make_backend(_script(tmp_path, [_candidate_reply("x_velocity")]), audit_dir=tmp_path)
    reframer = Reframer(SRRConfig(), CARD, backend, action_dim=6, permutations=100)
    ev = _structural_evidence()
    ev.d = {**ev.d, "tpd": 3.0, "peg": -3.0}  # readings the monitor's rules would turn into hypotheses

    def proxy(program, s):  # type: ignore[no-untyped-def]
        return CARD.feature_values(s)["x_velocity"]

    reframer.reframe(tmp_path / "iv", example_program("halfcheetah", 0), ev, obs,
                     CARD.feature_values(obs)["x_velocity"], obs, actions, proxy, seed=0)
    assert json.loads((tmp_path / "iv" / "evidence.json").read_text())["hypotheses"] == []
