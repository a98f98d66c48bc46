"""LaRe's static latent-reward program: obtained once through the reward-engineer backends and the
factor checks, saved in the run directory, never asked for again."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mira.baselines.config import LaReConfig
from mira.baselines.lare import (
    PROGRAM_FILE,
    SYNTHESIS_FILE,
    LaReReward,
    ProgramFactors,
    lare_messages,
    lare_program,
)
from mira.engineer.offline_lsfs import synthesize
from mira.errors import UsageError
from mira.llm.base import LLMReply, LLMRequest
from mira.llm.config import LLMConfig
from mira.tasks.card import load_task


class Refuses:
    """A backend that must not be called."""

    name = "refuses"
    model = "none"

    def complete(self, request: LLMRequest) -> LLMReply:
        raise AssertionError("the LLM was asked again")


def _good_reply(card_name: str = "halfcheetah", action_dim: int = 6) -> str:
    card = load_task(card_name)
    program = synthesize({"task": card.name, "action_dim": action_dim,
                          "features": [{"name": f.name, "units": f.units, "doc": f.doc} for f in card.features]})
    program.pop("engineer")
    return json.dumps(program)


def test_offline_engineer_gives_its_lsfs_program_and_it_is_saved(tmp_path: Path) -> None:
    card = load_task("halfcheetah")
    program, origin = lare_program(card, tmp_path, LLMConfig())
    assert program.names == ["r_vel", "r_upright", "r_stable", "r_ctrl"]
    assert "offline" in origin
    assert (tmp_path / PROGRAM_FILE).is_file()
    record = json.loads((tmp_path / SYNTHESIS_FILE).read_text())
    assert record["attempts"][0]["ok"] and record["factors"] == program.names
    exchanges = [json.loads(line) for line in (tmp_path / "llm" / "exchanges.jsonl").read_text().splitlines()]
    assert exchanges[0]["purpose"] == "lare"
    # A resumed run reads the saved program and never asks again.
    again, origin2 = lare_program(card, tmp_path, LLMConfig(), backend=Refuses())
    assert again == program and "saved" in origin2


def test_rejected_reply_is_shown_back_and_the_retry_is_used(tmp_path: Path) -> None:
    bad = {"task": "halfcheetah", "version": 0, "factors": [
        {"name": "r_bad", "type": "PHI", "code": "def r_bad(s):\n    import os\n    return s.x_velocity\n"}]}
    script = tmp_path / "replies.jsonl"
    script.write_text(json.dumps({"content": json.dumps(bad)}) + "\n" + json.dumps({"content": _good_reply()}) + "\n")
    run = tmp_path / "run"
    program, _ = lare_program(load_task("halfcheetah"), run, LLMConfig(backend=f"script:{script}"))
    assert "r_vel" in program.names
    attempts = json.loads((run / SYNTHESIS_FILE).read_text())["attempts"]
    assert [a["ok"] for a in attempts] == [False, True]
    assert any("r_bad" in r for r in attempts[0]["reasons"])
    exchanges = [json.loads(line) for line in (run / "llm" / "exchanges.jsonl").read_text().splitlines()]
    second = [e for e in exchanges if e.get("kind") == "exchange"][1]
    assert second["messages"][-2]["role"] == "assistant"
    assert "rejected" in second["messages"][-1]["content"]


def test_no_admissible_program_is_a_usage_error(tmp_path: Path) -> None:
    script = tmp_path / "replies.jsonl"
    script.write_text(json.dumps({"content": "I cannot help with that."}) + "\n")
    with pytest.raises(UsageError, match=r"no admissible .* after 1 request\(s\)"):
        lare_program(load_task("halfcheetah"), tmp_path / "run", LLMConfig(backend=f"script:{script}", followups=0))


def test_requests_are_the_runs_followups_plus_one(tmp_path: Path) -> None:
    """LaRe asks at most ``llm.followups + 1`` times (3 at the default 2 follow-ups)."""
    script = tmp_path / "replies.jsonl"
    script.write_text((json.dumps({"content": "I cannot help with that."}) + "\n") * 3)
    with pytest.raises(UsageError, match=r"after 3 request\(s\)"):
        lare_program(load_task("halfcheetah"), tmp_path / "run", LLMConfig(backend=f"script:{script}"))


def test_prompt_is_lsfs_plus_the_latent_reward_section() -> None:
    card = load_task("humanoidstandup")
    messages = lare_messages(card, 17)
    assert [m["role"] for m in messages] == ["system", "user"]
    user = messages[-1]["content"]
    assert "LATENT REWARD" in user and "s.torso_height" in user and "[B, 17]" in user


def test_program_factors_feed_the_decoder(tmp_path: Path) -> None:
    card = load_task("humanoidstandup")
    card.bind(348)
    program, _ = lare_program(card, tmp_path, LLMConfig())
    factors = ProgramFactors(program, card)
    rng = np.random.default_rng(0)
    obs, act = rng.standard_normal((7, 348)), rng.uniform(-1, 1, (7, 17))
    both = factors.both(obs, act)
    assert both.shape == (7, len(factors.names)) and np.isfinite(both).all()
    np.testing.assert_allclose(both, np.concatenate((factors.phi(obs), factors.aux(obs, act)), axis=1))
    source = LaReReward(factors, LaReConfig())
    assert source.describe()["factors"] == factors.names

