"""SRR (Algorithm 2) on real states with the real checks; the LLM is a scripted backend."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mira.engineer.backends import make_backend
from mira.engineer.srr_prompt import Evidence
from mira.factors import example_program
from mira.factors.sandbox import collect_states
from mira.srr.config import SRRConfig
from mira.srr.efficacy import proxy_efficacy, roc_auc
from mira.srr.hypotheses import EditSurrogate, rule_hypotheses
from mira.srr.reframe import Reframer, allowed_r2_loss
from mira.tasks import load_task

GATED_VEL = "def r_vel(s):\n    return s.x_velocity * (1.0 - np.tanh(2.0 * np.square(s.pitch)))\n"


def _reply(code: str = GATED_VEL, operator: str = "Gate") -> str:
    cand = {"edits": [{"operator": operator, "targets": ["r_vel"], "params": {}, "justification": "low PVC"}],
            "updated_factors": [{"name": "r_vel", "type": "PHI", "code": code, "doc": "posture-gated velocity",
                                 "units": "m/s", "range_hint": "[-15, 15]"}]}
    return "Here is my answer:\n```json\n" + json.dumps({"candidates": [cand]}) + "\n```"


def _evidence() -> Evidence:
    d = {"peg": 0.0, "tpd": 0.0, "pvc": -2.5, "fap": 0.3, "rpe": 0.5}
    return Evidence(step=5000, d=d, d_raw=d, score=12.0, threshold=8.0,
                    gradient={"peg": 0.0, "tpd": 0.0, "pvc": 1.5, "fap": 0.0, "rpe": -0.2},
                    contributors=[{"metric": "pvc", "value": -2.5, "gradient": 1.5,
                                   "reading": "potential decoupled from return"}],
                    recent_return=-10.0, baseline_return=5.0, stagnation_band=None, attention={"r_vel": 0.8})


@pytest.fixture(scope="module")
def states() -> tuple[np.ndarray, np.ndarray]:
    return collect_states(load_task("halfcheetah"), 400, seed=3)


def _reframe(tmp_path: Path, replies: list[str], proxy_sign: float, states: tuple[np.ndarray, np.ndarray],  # type: ignore[no-untyped-def]
             explain=None):
    card = load_task("halfcheetah")
    script = tmp_path / "replies.jsonl"
    script.write_text("".join(json.dumps({"content": r}) + "\n" for r in replies))
    backend = make_backend(f"script:{script}", audit_dir=tmp_path)
    obs, actions = states
    values = card.feature_values(obs)["x_velocity"]

    def proxy(program, s):  # type: ignore[no-untyped-def]
        assert program.version == 1  # only candidates reach the proxy
        return proxy_sign * card.feature_values(s)["x_velocity"]

    reframer = Reframer(SRRConfig(), card, backend, action_dim=6, permutations=200)
    return reframer.reframe(tmp_path / "iv", example_program("halfcheetah", 0), _evidence(), obs, values, obs, actions,
                            proxy, seed=0, explain=explain)


def test_useful_candidate_is_accepted_with_audit_trail(tmp_path: Path, states: tuple[np.ndarray, np.ndarray]) -> None:
    decision = _reframe(tmp_path, [_reply()], +1.0, states)
    assert decision.accepted and decision.program.version == 1 and decision.operators == ["Gate"]
    assert "tanh" in decision.program.factor("r_vel").code
    for name in ("evidence.json", "request.json", "response.txt", "candidates.json", "decision.json", "accepted.diff"):
        assert (tmp_path / "iv" / name).is_file(), name
    record = json.loads((tmp_path / "iv" / "candidates.json").read_text())[0]
    assert record["verdicts"]["efficacy"]["auc"] > 0.9 and record["verdicts"]["efficacy"]["auc_p"] < 0.05
    assert "potential decoupled from return" in (tmp_path / "iv" / "request.json").read_text()


def test_valid_but_harmful_candidate_is_rejected_with_backoff(tmp_path: Path,
                                                             states: tuple[np.ndarray, np.ndarray]) -> None:
    decision = _reframe(tmp_path, [_reply()], -1.0, states)
    assert not decision.accepted and decision.backoff and not decision.failed
    assert decision.program.version == 0
    assert "proxy efficacy" in decision.reason


@pytest.mark.parametrize(("candidate_r2", "accepted"), [(0.90, True), (0.80, False)])
def test_returns_veto_a_candidate_that_explains_them_worse(tmp_path: Path, states: tuple[np.ndarray, np.ndarray],
                                                          candidate_r2: float, accepted: bool) -> None:
    """The proxy test passes either way; a candidate whose out-of-sample R² of the returns falls by more than
    ``MAX_R2_LOSS`` (0.95 → 0.80) is refused, a small loss (0.95 → 0.90) within the tolerance is not."""
    def explain(program):  # type: ignore[no-untyped-def]
        return 0.95 if program.version == 0 else candidate_r2

    decision = _reframe(tmp_path, [_reply()], +1.0, states, explain=explain)
    assert decision.accepted is accepted
    record = json.loads((tmp_path / "iv" / "candidates.json").read_text())[0]
    assert record["verdicts"]["efficacy"]["auc"] > 0.9  # the proxy test alone would have accepted it
    assert record["verdicts"]["returns"]["harms"] is (not accepted)
    if not accepted:
        assert decision.backoff and "return explanation" in decision.reason and "0.950 -> 0.800" in decision.reason


@pytest.mark.parametrize(("candidate_r2", "accepted"), [(0.99997, True), (0.99, False)])
def test_returns_veto_scales_with_what_the_program_leaves_unexplained(
        tmp_path: Path, states: tuple[np.ndarray, np.ndarray], candidate_r2: float, accepted: bool) -> None:
    """A program that explains the returns almost exactly (R² 0.99998) refuses a candidate at 0.99 (a loss
    below ``MAX_R2_LOSS`` that leaves 500 times as much unexplained) and accepts one within noise of it."""
    def explain(program):  # type: ignore[no-untyped-def]
        return 0.99998 if program.version == 0 else candidate_r2

    decision = _reframe(tmp_path, [_reply()], +1.0, states, explain=explain)
    assert decision.accepted is accepted
    record = json.loads((tmp_path / "iv" / "candidates.json").read_text())[0]
    assert record["verdicts"]["returns"]["allowed_loss"] == pytest.approx(2e-5)
    if not accepted:
        assert "0.999980 -> 0.990" in decision.reason


def test_allowed_r2_loss() -> None:
    assert allowed_r2_loss(0.5, 0.05, 1.0) == 0.05
    assert allowed_r2_loss(0.99, 0.05, 1.0) == pytest.approx(0.01)
    assert allowed_r2_loss(1.0, 0.05, 1.0) == 0.0


def test_invalid_reply_is_rejected_before_any_check(tmp_path: Path, states: tuple[np.ndarray, np.ndarray]) -> None:
    decision = _reframe(tmp_path, ["I would gate the velocity on posture."], +1.0, states)
    assert not decision.accepted and decision.failed and "before any check" in decision.reason
    assert not (tmp_path / "iv" / "candidates.json").exists()


def test_hostile_candidate_never_runs(tmp_path: Path, states: tuple[np.ndarray, np.ndarray]) -> None:
    marker = tmp_path / "pwned"
    code = f"def r_vel(s):\n    open('{marker}', 'w')\n    return s.x_velocity\n"
    decision = _reframe(tmp_path, [_reply(code)], +1.0, states)
    assert not decision.accepted and "static integrity" in decision.reason
    assert not marker.exists()


def test_rules_map_evidence_to_operators() -> None:
    hyps = rule_hypotheses({"pvc": -2.0, "rpe": 0.0, "fap": 0.5, "tpd": 0.0, "peg": 0.0}, return_is_poor=False)
    assert hyps[0].operator == "Gate"
    hyps = rule_hypotheses({"pvc": 0.5, "rpe": 2.0, "fap": 0.5, "tpd": 0.0, "peg": -1.5}, return_is_poor=True)
    assert hyps[0].operator == "Add"


def test_surrogate_learns_from_accepted_edits() -> None:
    sur = EditSurrogate()
    before = sur.predict(["Gate"]).copy()
    observed = np.array([0.0, 0.0, 2.0, 0.0, -1.0])
    for _ in range(10):
        sur.observe(["Gate"], np.zeros(5), observed)
    assert np.allclose(sur.predict(["Gate"]), observed, atol=0.01)
    assert not np.allclose(before, observed)
    assert sur.score(["Gate"], np.array([0, 0, 1.0, 0, -1.0]), complexity=1.0) > 0


def test_auc_and_permutation_test() -> None:
    assert roc_auc(np.array([3.0, 4.0]), np.array([1.0, 2.0])) == 1.0
    assert roc_auc(np.array([1.0, 2.0]), np.array([1.0, 2.0])) == 0.5
    rng = np.random.default_rng(0)
    values = rng.normal(size=300)
    good = proxy_efficacy(values + 0.1 * rng.normal(size=300), values, n_perm=200)
    assert good.auc > 0.95 and good.auc_p < 0.01 and good.spearman > 0.9
    noise = proxy_efficacy(rng.normal(size=300), values, n_perm=200)
    assert noise.auc_p > 0.01
