"""LSFS prompt construction and the strict reader of LLM replies."""

from __future__ import annotations

import json

import pytest

from mira.engineer.lsfs_prompt import build_lsfs_messages, parse_program_reply
from mira.factors import ProgramParseError, check_program, example_program
from mira.tasks import load_task

CARD = load_task("halfcheetah", check_env=False)
REPLY = {
    "subgoals": ["run forward", "stay level"],
    "factors": [
        {
            "name": "r_vel",
            "type": "PHI",
            "code": "def r_vel(s):\n    return s.x_velocity\n",
            "doc": "forward velocity",
            "units": "m/s",
            "range_hint": "[-15, 15]",
        },
        {
            "name": "r_ctrl",
            "type": "AUX",
            "code": "def r_ctrl(s, a):\n    return -0.1 * np.sum(a * a, axis=-1)\n",
            "doc": "effort",
            "units": "1",
            "range_hint": "[-0.6, 0]",
        },
    ],
    "rationale": "progress plus effort",
}


def test_messages_follow_the_structured_chain_of_thought() -> None:
    messages = build_lsfs_messages(CARD, action_dim=6)
    assert [m["role"] for m in messages] == ["system", "user"]
    system, user = messages[0]["content"], messages[1]["content"]
    assert "reward engineer" in system
    for section in (
        "# 1. Task context",
        "# 2. Hierarchical task decomposition",
        "# 3. Reward-factor identification",
        "# 4. Executable code",
        "# 5. Output format",
    ):
        assert section in user
    assert CARD.description.splitlines()[0] in user
    for name in CARD.feature_names:
        assert f"s.{name}" in user
    assert "[B, 6]" in user and "np.tanh" in user and "PHI" in user and "AUX" in user
    assert "$" not in user.replace("$$", "")  # every placeholder was filled


def test_template_values_are_inserted_verbatim() -> None:
    card = load_task("halfcheetah", check_env=False)
    card.description = "Run. $syntax ${evil} $$"
    user = build_lsfs_messages(card)[1]["content"]
    assert "Run. $syntax ${evil} $$" in user


@pytest.mark.parametrize(
    "wrap",
    [
        lambda j: j,
        lambda j: f"```json\n{j}\n```",
        lambda j: f"Here is the program you asked for:\n\n```\n{j}\n```\nLet me know if you need changes.",
        lambda j: f"Sure! {j} Hope this helps.",
    ],
)
def test_reply_shapes_real_models_send(wrap: object) -> None:
    program = parse_program_reply(wrap(json.dumps(REPLY, indent=2)), CARD)  # type: ignore[operator]
    assert program.task == "halfcheetah" and program.version == 0
    assert program.names == ["r_vel", "r_ctrl"] and [f.type for f in program.factors] == ["PHI", "AUX"]
    assert "run forward" in program.rationale and "progress plus effort" in program.rationale
    assert check_program(program, CARD).ok


def test_reply_quirks_are_normalised() -> None:
    reply = json.loads(json.dumps(REPLY))
    reply["factors"][0]["code"] = ["def r_vel(s):", "    return s.x_velocity"]
    reply["factors"][0]["type"] = "phi"
    reply["factors"][0]["note"] = "models add fields"
    program = parse_program_reply(json.dumps(reply), None, task_name="halfcheetah")
    assert program.factor("r_vel").code == "def r_vel(s):\n    return s.x_velocity\n"
    assert program.factor("r_vel").type == "PHI"


@pytest.mark.parametrize(
    "text,fragment",
    [
        ("", "empty"),
        ("I cannot help with that.", "no JSON object"),
        ('{"factors": [1, 2],}', "not valid JSON"),
        ('{"program": {"factors": []}}', "no JSON object with a 'factors'"),
        ('{"factors": []}', "non-empty list"),
        ('{"factors": "r_vel"}', "non-empty list"),
        ('{"factors": [{"name": "r", "type": "PHI"}]}', "missing required field 'code'"),
        ('{"factors": [{"name": "r", "type": "Q", "code": "def r(s):\\n    return s.pitch\\n"}]}', "unknown"),
        (
            '{"factors": [{"name": "r", "type": "PHI", "code": "def r(s):\\n    return a[:, 0]\\n"}]}',
            "state-only",
        ),
        (json.dumps({"factors": [REPLY["factors"][0], REPLY["factors"][0]]}), "duplicate"),
        ("x" * 300_000, "at most"),
    ],
)
def test_malformed_replies_are_rejected_clearly(text: str, fragment: str) -> None:
    with pytest.raises(ProgramParseError, match=fragment):
        parse_program_reply(text, CARD)


def test_example_program_as_a_reply_round_trips() -> None:
    program = example_program("halfcheetah", 0)
    text = "```json\n" + json.dumps({"factors": [f.to_json() for f in program.factors]}) + "\n```"
    assert parse_program_reply(text, CARD).factors == program.factors
