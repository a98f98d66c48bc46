"""Stuck learning: the plateau detector, shaping terms outside the fitted reward, the escape edit and its
probation (the paper's case study II)."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch

from conftest import _load_bench
from mira.engineer.backends import make_backend
from mira.engineer.offline_srr import propose
from mira.engineer.srr_prompt import Evidence, build_srr_request
from mira.explain import explain
from mira.factors import example_program
from mira.factors.program import Factor, FactorProgram
from mira.factors.sandbox import collect_states
from mira.mcm.plateau import (
    MIN_RISE,
    PATIENCE,
    WARMUP_CYCLES,
    WINDOW,
    PlateauDetector,
    first_states,
    late_states,
)
from mira.runio.csvlog import read_csv
from mira.shaping.factors import ProgramFactorSource
from mira.shaping.testing import fill_episodes, make_hars
from mira.srr.config import SRRConfig
from mira.srr.hypotheses import OPERATORS
from mira.srr.reframe import Reframer
from mira.tasks import load_task

SETTLED = np.full(200, 0.40) + np.linspace(-0.01, 0.01, 200)  # a sitting humanoid's late torso heights
VISITED = (0.10, 0.45)


def _feed(detector: PlateauDetector, returns: np.ndarray, settled: np.ndarray = SETTLED) -> list[int]:
    """The cycles at which the detector reports a plateau."""
    return [k for k, r in enumerate(returns) if detector.observe(1000 * k, float(r), settled, VISITED) is not None]


def test_the_detector_fires_on_a_stall_and_not_while_the_return_rises() -> None:
    rng = np.random.default_rng(0)
    cycles = WARMUP_CYCLES + 3 * WINDOW
    rising = 50_000 + 2_000 * np.arange(cycles) + rng.normal(0, 500, cycles)  # +4% per cycle at the start
    assert _feed(PlateauDetector("torso_height"), rising) == []
    # Rising for the warm-up, then flat around 130k with noise: reported once the flat windows compare.
    stalled = np.concatenate([np.linspace(50_000, 130_000, WARMUP_CYCLES),
                              130_000 + rng.normal(0, 1_000, 3 * WINDOW)])
    fired = _feed(PlateauDetector("torso_height"), stalled)
    assert fired and fired[0] >= WARMUP_CYCLES and fired[0] <= WARMUP_CYCLES + 2 * WINDOW + PATIENCE
    # Flat returns with states spread over the visited range: no band to escape from, no report.
    spread = np.linspace(*VISITED, 200)
    assert _feed(PlateauDetector("torso_height"), stalled, spread) == []


def test_a_flat_dip_after_the_warm_up_is_a_plateau_too() -> None:
    # High early returns (an untrained sitter), then a dip that stays flat: reported in the dip, where an
    # escape can still shape the recovery, not only once the run is back at its best.
    rng = np.random.default_rng(2)
    early = 120_000 + rng.normal(0, 500, WARMUP_CYCLES // 2)
    dip = 80_000 + rng.normal(0, 500, WARMUP_CYCLES // 2 + 3 * WINDOW)
    fired = _feed(PlateauDetector("torso_height"), np.concatenate([early, dip]))
    assert fired and len(early) <= fired[0] < len(early) + len(dip)


def _medians_level(returns: np.ndarray) -> list[int]:
    """The cycles at which the last window's median is less than MIN_RISE above the window's before."""
    def median(lo: int, hi: int) -> float:
        return float(np.median(returns[lo:hi]))
    return [k for k in range(2 * WINDOW - 1, len(returns))
            if median(k - WINDOW + 1, k + 1) < (1 + MIN_RISE) * median(k - 2 * WINDOW + 1, k - WINDOW + 1)]


def test_level_medians_on_a_noisy_climb_are_not_a_plateau() -> None:
    # Humanoid's held-out return: a climb with 15% noise per cycle and a flat stretch of 20 cycles in it.
    rng = np.random.default_rng(3)
    level = np.concatenate([np.linspace(300, 450, WARMUP_CYCLES), np.full(2 * WINDOW, 450.0),
                            np.linspace(450, 600, 3 * WINDOW)])
    returns = level * (1 + 0.15 * rng.standard_normal(level.size))
    level_at = [k for k in _medians_level(returns) if k >= WARMUP_CYCLES - 1]
    assert any(b == a + 1 for a, b in itertools.pairwise(level_at))  # the medians alone would report
    assert _feed(PlateauDetector("torso_height"), returns) == []


def test_a_sudden_drop_is_not_a_plateau_until_the_return_stays_down() -> None:
    rng = np.random.default_rng(4)
    drop = WARMUP_CYCLES + 2 * WINDOW
    returns = np.concatenate([np.linspace(60_000, 130_000, drop), np.full(3 * WINDOW, 90_000.0)])
    returns += rng.normal(0, 500, returns.size)  # a climb, then a fall to a lower level that holds
    assert next(k for k in _medians_level(returns) if k > drop) < drop + WINDOW  # the medians alone: at once
    fired = _feed(PlateauDetector("torso_height"), returns)
    # Reported only once the trend over both windows is flat again: the drop has left them.
    assert fired and fired[0] >= drop + 2 * WINDOW - 1


def test_a_report_carries_the_band_and_the_paper_signature() -> None:
    detector = PlateauDetector("torso_height")
    found = None
    for k in range(WARMUP_CYCLES + 2 * WINDOW + PATIENCE):
        found = detector.observe(1000 * k, 130_000.0, SETTLED, VISITED, peg=-1.8, rpe=2.4) or found
    assert found is not None
    assert found.feature == "torso_height" and abs(found.center - 0.40) < 0.01 and found.halfwidth < 0.01
    assert found.as_dict()["d_peg"] == -1.8 and found.as_dict()["d_rpe"] == 2.4 and found.rise < MIN_RISE
    assert found.trend == 0.0 and found.trend_se == 0.0  # a constant return: flat, and surely so
    # Reported once: the history restarts, so the next report needs a stall of its own.
    assert detector.observe(10**6, 130_000.0, SETTLED, VISITED) is None


def test_a_restored_detector_decides_as_the_original() -> None:
    rng = np.random.default_rng(1)
    returns = 100_000 + rng.normal(0, 3_000, WARMUP_CYCLES + 4 * WINDOW)
    original, restored = PlateauDetector("torso_height"), PlateauDetector("torso_height")
    half = len(returns) // 2 + 3
    _feed(original, returns[:half])
    restored.load_state_dict(json.loads(json.dumps(original.state_dict())))
    assert _feed(original, returns[half:]) == _feed(restored, returns[half:])


def test_late_states_are_the_second_half_of_each_episode() -> None:
    values = np.arange(10.0)
    episodes = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1])
    assert late_states(values, episodes).tolist() == [2.0, 3.0, 7.0, 8.0, 9.0]


# ------------------------------------------------------------------------- shaping outside the head

HS_OBS = 348
"""HumanoidStandup-v5's observation size."""
ESCAPE_CODE = "def psi_up(s):\n    return 5.0 * (1.0 + np.tanh((s.torso_height - 0.5) / 0.2))\n"


def _with_shape(program: FactorProgram, code: str = ESCAPE_CODE, hint: str = "[0, 10]") -> FactorProgram:
    shape = Factor("psi_up", "SHAPE", code, doc="escape potential", units="1", range_hint=hint)
    return program.with_factors([*program.factors, shape], version=program.version + 1)


def test_a_shape_factor_changes_the_reward_by_its_potential_difference_and_not_the_head() -> None:
    card = load_task("humanoidstandup", check_env=False)
    card.bind(HS_OBS)
    plain = example_program("humanoidstandup", 0)
    shaped = _with_shape(plain)
    gamma = 0.97
    sources = {}
    for label, program in (("plain", plain), ("shaped", shaped)):
        src, buf = make_hars(ProgramFactorSource(program, card), obs_dim=card.obs_dim, act_dim=17, capacity=512,
                             gamma=gamma, card=card)
        rng = np.random.default_rng(0)
        fill_episodes(src, buf, [30, 30, 30], rng)
        (truncated,) = fill_episodes(src, buf, [25], rng)
        (terminal,) = fill_episodes(src, buf, [20], rng, terminate=True)
        sources[label] = (src, buf, truncated, terminal)
    plain_src, shaped_src = sources["plain"][0], sources["shaped"][0]
    # The head is fitted over PHI and AUX factors alone: the same weights with or without the shaping term.
    assert plain_src.head.describe()["weights"] == shaped_src.head.describe()["weights"]
    assert "psi_up" not in shaped_src.head.describe()["weights"]
    psi = ProgramFactorSource(shaped, card).shape
    for rows, terminal in ((sources["shaped"][2], False), (sources["shaped"][3], True)):
        batch = sources["shaped"][1].gather(rows)
        with torch.no_grad():
            r_plain = plain_src.relabel(sources["plain"][1].gather(rows)).double().numpy()
            r_shaped = shaped_src.relabel(batch).double().numpy()
        psi_s = psi(batch.obs.numpy().astype(np.float64))
        psi_next = psi(batch.next_obs.numpy().astype(np.float64)) * (1.0 - batch.terminated.numpy())
        np.testing.assert_allclose(r_shaped - r_plain, gamma * psi_next - psi_s, rtol=1e-5, atol=1e-4)
        # Telescoping: over an episode the discounted shaping sums to γ^T Ψ(s_T) − Ψ(s_0) (0 after a terminal).
        disc = gamma ** np.arange(len(rows))
        end = 0.0 if terminal else gamma ** len(rows) * psi_next[-1]
        assert float((disc * (r_shaped - r_plain)).sum()) == pytest.approx(end - psi_s[0], rel=1e-4, abs=1e-3)


def test_shape_factors_are_state_only_and_their_values_survive_a_checkpoint() -> None:
    card = load_task("humanoidstandup", check_env=False)
    card.bind(HS_OBS)
    with pytest.raises(Exception, match="state-only"):
        _with_shape(example_program("humanoidstandup", 0), "def psi_up(s, a):\n    return a[:, 0]\n")
    shaped = _with_shape(example_program("humanoidstandup", 0))
    src, buf = make_hars(ProgramFactorSource(shaped, card), obs_dim=card.obs_dim, act_dim=17, card=card)
    fill_episodes(src, buf, [40, 40], np.random.default_rng(2))
    state = src.state_dict()
    assert "psi" in state["columns"]
    again, buf2 = make_hars(ProgramFactorSource(shaped, card), obs_dim=card.obs_dim, act_dim=17, card=card)
    fill_episodes(again, buf2, [40, 40], np.random.default_rng(2))
    again.load_state_dict(state)
    batch = buf.gather(np.arange(60))
    with torch.no_grad():
        assert torch.equal(src.relabel(batch), again.relabel(buf2.gather(np.arange(60))))


# ------------------------------------------------------------------------------ the escape edit

def _plateau_evidence() -> Evidence:
    """The plateau of a sitting HumanoidStandup policy, as the recorded LLM prompt states it."""
    evidence: Evidence = _load_bench("llm/plateau").evidence()
    return evidence


def test_the_offline_engineer_answers_a_plateau_with_a_bounded_potential_above_the_band() -> None:
    card = load_task("humanoidstandup", check_env=False)
    request = build_srr_request(card, example_program("humanoidstandup", 0), _plateau_evidence(), [], 3, OPERATORS,
                                17)
    prompt = request.messages[1]["content"]
    assert "plateau detector" in prompt and "settled band: torso_height = 0.4 ± 0.01" in prompt
    reply = propose(request.context)
    (cand,) = reply["candidates"]
    (edit,) = cand["edits"]
    new = cand["updated_factors"][-1]
    assert edit["operator"] == "Add" and new["type"] == "SHAPE" and new["name"] == "psi_escape"
    namespace: dict[str, Any] = {"np": np}
    exec(new["code"], namespace)
    z = np.array([0.1, 0.40, 0.6, 1.4])
    psi = namespace["psi_escape"](SimpleNamespace(torso_height=z))
    height = 20 * 130.0  # ESCAPE_STEPS steps of the plateau's reward per step
    assert psi[1] < 0.3 * height and psi[0] < psi[1] < psi[2] < psi[3] <= height  # a ramp upward from the band
    assert json.loads(new["range_hint"]) == [0, height]


def test_the_ramp_spans_half_the_climb_from_where_the_episodes_start() -> None:
    # A policy that sits still visits a narrow range; the climb from the episodes' start to the band sets
    # the ramp's scale then (section 5.3.2's escape reaches toward standing, not a few centimetres up).
    card = load_task("humanoidstandup", check_env=False)
    evidence = _plateau_evidence()
    assert evidence.plateau is not None
    narrow = {**evidence.plateau, "visited": [0.30, 0.42]}

    def ramp(plateau: dict[str, Any]) -> tuple[float, str]:
        evidence.plateau = plateau
        request = build_srr_request(card, example_program("humanoidstandup", 0), evidence, [], 3, OPERATORS, 17)
        (cand,) = propose(request.context)["candidates"]
        return float(cand["edits"][0]["params"]["ramp_width"]), request.messages[1]["content"]

    width, prompt = ramp(narrow)
    assert width == pytest.approx(0.25 * 0.12) and "episodes start at" not in prompt
    width, prompt = ramp({**narrow, "start": 0.1})
    assert width == pytest.approx(0.5 * (0.4 - 0.1)) and "the episodes start at 0.1" in prompt


def test_first_states_are_each_episode_first_value() -> None:
    episode = np.array([0, 0, 0, 1, 1, 2])
    assert first_states(np.array([0.1, 0.2, 0.3, 0.12, 0.5, 0.09]), episode).tolist() == [0.1, 0.12, 0.09]


def _reframe_escape(tmp_path: Path, reply: dict[str, Any], states: tuple[np.ndarray, np.ndarray]) -> Any:
    card = load_task("humanoidstandup")
    script = tmp_path / "replies.jsonl"
    script.write_text(json.dumps({"content": json.dumps(reply)}) + "\n")
    backend = make_backend(f"script:{script}", audit_dir=tmp_path)
    obs, actions = states
    values = -card.feature_values(obs)["torso_height"]  # the proxy test would refuse anything

    def proxy(program: FactorProgram, s: np.ndarray) -> np.ndarray:
        return np.asarray(card.feature_values(s)["torso_height"], dtype=np.float64)

    def explain(program: FactorProgram) -> float:
        return 0.99  # a shaping term adds nothing to the returns' explanation: no gain, no loss

    reframer = Reframer(SRRConfig(), card, backend, action_dim=17, permutations=100)
    return reframer.reframe(tmp_path / "iv", example_program("humanoidstandup", 0), _plateau_evidence(), obs, values,
                            obs, actions, proxy, seed=0, explain=explain)


@pytest.fixture(scope="module")
def hs_states() -> tuple[np.ndarray, np.ndarray]:
    return collect_states(load_task("humanoidstandup"), 300, seed=4)


def test_the_escape_passes_verification_where_the_returns_and_proxy_cannot_judge_it(
        tmp_path: Path, hs_states: tuple[np.ndarray, np.ndarray]) -> None:
    card = load_task("humanoidstandup", check_env=False)
    request = build_srr_request(card, example_program("humanoidstandup", 0), _plateau_evidence(), [], 3, OPERATORS,
                                17)
    decision = _reframe_escape(tmp_path, propose(request.context), hs_states)
    assert decision.accepted, decision.reason
    assert [f.name for f in decision.program.shape_factors] == ["psi_escape"]
    record = json.loads((tmp_path / "iv" / "candidates.json").read_text())[0]
    assert record["verdicts"]["shaping"]["passed"] and "efficacy" not in record["verdicts"]


@pytest.mark.parametrize(("code", "hint", "why"), [
    (ESCAPE_CODE, "(-inf, inf)", "finite range_hint"),
    ("def psi_up(s):\n    return 1e6 * (1.0 + np.tanh(s.torso_height))\n", "[0, 2e6]", "wider than 100 steps"),
    (ESCAPE_CODE, "[0, 0.01]", "leave its declared range"),
])
def test_an_unbounded_or_oversized_shaping_term_is_refused(tmp_path: Path, hs_states: tuple[np.ndarray, np.ndarray],
                                                           code: str, hint: str, why: str) -> None:
    factors = [*example_program("humanoidstandup", 0).to_json()["factors"],
               {"name": "psi_up", "type": "SHAPE", "code": code, "doc": "d", "units": "1", "range_hint": hint}]
    reply = {"candidates": [{"edits": [{"operator": "Add", "targets": ["psi_up"], "params": {"type": "SHAPE"},
                                        "justification": "escape"}], "updated_factors": factors}]}
    decision = _reframe_escape(tmp_path, reply, hs_states)
    assert not decision.accepted and why in decision.reason


# -------------------------------------------------------------------------- in a run, and resumed

PATCHED_CLI = [sys.executable, "-c", "; ".join([
    "import sys", "import mira.mcm.plateau as P", "import mira.outer.loop as L",
    # A stall reported from the third cycle on, on a band of any width; an escape that never pays.
    "P.WARMUP_CYCLES = 3", "P.WINDOW = 1", "P.PATIENCE = 1", "P.MIN_RISE = 10.0", "P.MAX_BAND_SHARE = 10.0",
    "L.MIN_RISE = 10.0", "from mira.cli import main", "sys.exit(main(sys.argv[1:]))"])]
RUN_ARGS = ["train", "--task", "humanoidstandup", "--method", "mira", "--steps", "2400", "--seed", "0",
            "--learning-starts", "400", "--batch-size", "32", "--hidden", "32,32", "--eval-every", "400",
            "--eval-episodes", "1", "--max-episode-steps", "200", "--checkpoint-every", "200", "--log-every", "200",
            "--threads", "1", "--quiet", "--set", "mira.mcm.delta_t=200", "--set", "mira.holdout_episodes=1",
            "--set", "mira.mcm.k_cool=3"]


def _cli(out: Path, failpoints: str = "", resume: bool = False) -> int:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MIRA_FAILPOINTS": failpoints}
    args = ["train", "--resume", str(out), "--quiet"] if resume else [*RUN_ARGS, "--out", str(out)]
    return subprocess.run([*PATCHED_CLI, *args], env=env, capture_output=True, text=True, timeout=900).returncode


def _outcome(run: Path) -> dict[str, Any]:
    return {"eval": [(r["step"], r["return_mean"]) for r in read_csv(run / "eval.csv")],
            # Every figure of the training log but the wall-clock speed.
            "train": [{k: v for k, v in r.items() if k != "steps_per_s"} for r in read_csv(run / "train.csv")],
            "plateau": read_csv(run / "plateau.csv"),
            "programs": {p.name: p.read_text() for p in sorted((run / "programs").glob("v*.json"))}}


@pytest.mark.slow
def test_an_escape_is_installed_rolled_back_and_resumed_bit_for_bit(tmp_path: Path) -> None:
    reference = tmp_path / "reference"
    assert _cli(reference) == 0
    events = [r["event"] for r in read_csv(reference / "plateau.csv")]
    assert events[:3] == ["plateau", "escape_rolled_back", "plateau"]
    # A plateau whose escape could not be judged before the last step is left unanswered, and said so.
    rows = read_csv(reference / "plateau.csv")
    assert events[-2:] == ["plateau", "too_late"] and rows[-1]["step"] == rows[-2]["step"]
    assert int(rows[-1]["step"]) + 3 * 200 > 2400 and int(rows[2]["step"]) + 3 * 200 <= 2400
    assert max(int(p.stem[1:]) for p in (reference / "programs").glob("v*.json")) == int(rows[-1]["version"])
    story = explain(reference)
    assert f"Plateau at step {rows[0]['step']}" in story and f"No escape at step {rows[-1]['step']}" in story
    programs = {p.stem: json.loads(p.read_text()) for p in (reference / "programs").glob("v*.json")}
    assert [f["type"] for f in programs["v001"]["factors"]][-1] == "SHAPE"
    assert programs["v002"]["factors"] == programs["v000"]["factors"]  # the escape removed, the rest kept
    probation = json.loads(next((reference / "interventions").glob("000-*/probation.json")).read_text())
    assert probation["kept"] is False and probation["factors"] == ["psi_escape"]
    # Killed while the first escape is on probation, then resumed: the same run, bit for bit.
    first_plateau = int(read_csv(reference / "plateau.csv")[0]["step"])
    kill_at = first_plateau // 200 + 2  # the checkpoint after the escape's installation
    killed = tmp_path / "killed"
    assert _cli(killed, f"checkpoint.after_payload:{kill_at}") != 0
    assert _cli(killed, resume=True) == 0
    assert _outcome(killed) == _outcome(reference)


ARCHIVE = Path(__file__).resolve().parents[1] / "bench" / "archive"


def test_on_the_archived_runs_it_reports_where_humanoidstandup_sits_and_not_where_humanoid_climbs() -> None:
    replay = _load_bench("plateau_replay")
    # Humanoid-v5 SAC at 100k climbs throughout (about 400 to 600); the medians alone reported twice per seed.
    for seed in range(3):
        run = ARCHIVE / f"hum100_sac_mira_s{seed}" / "humanoid" / "sac" / "mira" / f"seed{seed}"
        assert len(replay.recorded(run)) == 2 and replay.replay(run) == []
    # HumanoidStandup-v5 SAC without the monitor's edits sits at 131k-141k from 100k to 200k: reported.
    for seed in range(3):
        run = ARCHIVE / f"hs200_sac_mira_no_mcm_s{seed}" / "humanoidstandup" / "sac" / "mira-no-mcm" / f"seed{seed}"
        assert replay.replay(run), run
