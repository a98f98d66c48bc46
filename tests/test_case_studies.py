"""The two case studies of section 5.3, through the machinery a real LLM would use.

Each study trains a real HARS potential (FAB → VPM, the shipped initial program) on real MuJoCo
transitions with the episodic reward, measures the pathology on held-out real states with the
monitor's own metric functions, lets the real monitor (Algorithm 1, short warm-up) diagnose it
after a healthy phase, and hands the monitor's evidence to SRR exactly as the outer loop does: the
prompt goes through the LLM backend interface to the offline engineer, the reply is parsed,
checked statically, run in the sandbox and scored for proxy efficacy through the *frozen* FAB/VPM.
What must come out is the paper's edit: on HalfCheetah the velocity factor gated on posture after
potential–return decoupling; on HumanoidStandup an escape bonus at the stagnation band after
stagnation. The accepted program is then installed in HARS, which re-initialises ϕ, φ.

The pathologies are made to appear quickly (a few thousand random-gait steps instead of a long
run; on HalfCheetah half the episodes start on the cheetah's back, the posture the paper's agent
found) — the configuration the issue allows for tests; the defaults stay Table 1's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mira.engineer.backends import make_backend
from mira.engineer.srr_prompt import Evidence
from mira.factors import example_program
from mira.factors.sandbox import collect_states
from mira.mcm import MCMConfig, MetacognitiveMonitor
from mira.mcm.band import stagnation_band
from mira.mcm.metrics import d_pvc, d_rpe
from mira.shaping.config import HarsConfig
from mira.shaping.factors import ProgramFactorSource
from mira.shaping.source import HarsReward
from mira.shaping.testing import make_hars
from mira.srr.config import SRRConfig
from mira.srr.reframe import Reframer
from mira.tasks import load_task, make_env

pytestmark = pytest.mark.slow
GAMMA = 0.99


def _train_hars(task: str, episodes: int, length: int, on_back_every: int | None,
                updates: int) -> tuple[HarsReward, dict[str, np.ndarray]]:
    """HARS on ``episodes`` random-gait episodes; returns it and the last half of the episodes as a held-out set."""
    torch.manual_seed(0)
    card = load_task(task)
    env = make_env(card, seed=0, max_episode_steps=length)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]  # type: ignore[index]
    hars, buf = make_hars(ProgramFactorSource(example_program(task, 0), card), obs_dim=obs_dim, act_dim=act_dim,
                          capacity=episodes * length, config=HarsConfig(update_every=1), card=card, gamma=GAMMA)
    rng = np.random.default_rng(0)
    held: dict[str, list[np.ndarray]] = {"obs": [], "next_obs": [], "r": [], "value": [], "terminal": []}
    for ep in range(episodes):
        obs, _ = env.reset(seed=ep)
        if on_back_every and ep % on_back_every:
            sim = env.unwrapped
            qpos, qvel = sim.data.qpos.copy(), sim.data.qvel.copy()  # type: ignore[attr-defined]
            qpos[1] += 0.3
            qpos[2] += np.pi  # root pitch: on its back
            sim.set_state(qpos, qvel)  # type: ignore[attr-defined]
            obs = sim._get_obs()  # type: ignore[attr-defined]
        gait = rng.uniform(-1, 1, act_dim)  # each episode its own gait, so returns differ between episodes
        trace: dict[str, list] = {k: [] for k in held}
        done = False
        while not done:
            action = np.clip(gait + 0.3 * rng.standard_normal(act_dim), -1, 1).astype(np.float32)
            nxt, reward, terminated, truncated, info = env.step(action)
            row = buf.add(obs.astype(np.float32), action, float(reward), float(info["dense_reward"]),
                          nxt.astype(np.float32), terminated, truncated and not terminated, ep)
            hars.on_transition(row)
            for k, v in (("obs", obs), ("next_obs", nxt), ("r", reward), ("terminal", terminated)):
                trace[k].append(v)
            obs, done = nxt, terminated or truncated
        rows = buf.finish_episode(float(info["episode_return"]))
        hars.on_episode_end(rows, float(info["episode_return"]))
        if ep >= episodes // 2:
            # As the outer loop measures them: the episodic reward and its discounted return-to-go.
            r = np.asarray(trace["r"], dtype=np.float64)
            value = np.array([np.sum(r[i:] * GAMMA ** np.arange(len(r) - i)) for i in range(len(r))])
            for k in ("obs", "next_obs", "r", "terminal"):
                held[k].append(np.asarray(trace[k], dtype=np.float64))
            held["value"].append(value)
    for step in range(updates):
        batch = buf.sample(256, rng)
        hars.relabel(batch)
        hars.update(batch, step)
    return hars, {k: np.concatenate(v) for k, v in held.items()}


def _diagnose(pathological: dict[str, float], healthy: dict[str, float], returns: tuple[float, float]):  # type: ignore[no-untyped-def]
    """The real monitor: a healthy phase (noisy diagnostics, rising return), then the pathology until it
    triggers. Returns the triggering result."""
    monitor = MetacognitiveMonitor(MCMConfig(k_warm=4, buffer_min=4, min_scores=3, min_history=3, k_cool=3))
    rng = np.random.default_rng(1)
    names = ("peg", "tpd", "pvc", "fap", "rpe")
    spread = {"peg": 1e-5, "tpd": 0.02, "pvc": 0.05, "fap": 2e-3, "rpe": 0.05}
    for k in range(10):  # until the first cycle at which a trigger is possible at all
        raw = [healthy[n] + spread[n] * rng.standard_normal() for n in names]
        result = monitor.diagnose_raw(raw, step=1000 * (k + 1), smoothed_return=returns[0] + k)
        assert not result.trigger
    for k in range(10, 16):
        raw = [pathological.get(n, healthy[n]) + spread[n] * rng.standard_normal() for n in names]
        result = monitor.diagnose_raw(raw, step=1000 * (k + 1), smoothed_return=returns[1])
        if result.trigger:
            return result
    raise AssertionError("the monitor never diagnosed the pathology")


def _reframe(tmp_path: Path, task: str, hars: HarsReward, held: dict[str, np.ndarray], result, recent: float,  # type: ignore[no-untyped-def]
             band: dict[str, object] | None):
    card = load_task(task)
    ev = result.evidence()
    evidence = Evidence(step=result.step, d=ev["d"], d_raw=ev["d_raw"], score=ev["score"], threshold=ev["threshold"],
                        gradient=ev["gradient"], contributors=ev["contributors"], recent_return=recent,
                        baseline_return=float(result.baseline), stagnation_band=band,
                        attention=hars.attention(held["obs"]))
    backend = make_backend("offline", audit_dir=tmp_path)
    program = example_program(task, 0)
    sandbox_obs, sandbox_actions = collect_states(card, 512, seed=1)

    def proxy(candidate, states):  # type: ignore[no-untyped-def]
        return hars.proxy_potential(ProgramFactorSource(candidate, card), states).numpy()

    reframer = Reframer(SRRConfig(), card, backend, action_dim=int(sandbox_actions.shape[1]), permutations=500)
    decision = reframer.reframe(tmp_path / "iv", program, evidence, held["obs"], held["value"], sandbox_obs,
                                sandbox_actions, proxy, seed=0)
    exchanges = (tmp_path / "llm" / "exchanges.jsonl").read_text()
    assert "offline rule-based reward engineer" in exchanges  # saved like any LLM call, and says what it is
    return decision


def _install_and_check_reinit(hars: HarsReward, task: str, program) -> None:  # type: ignore[no-untyped-def]
    tce_before = {k: v.clone() for k, v in hars.nets.tce.state_dict().items()}
    fab_before = {k: v.clone() for k, v in hars.nets.fab.state_dict().items()}
    hars.set_program(ProgramFactorSource(program, load_task(task)))
    assert all(torch.equal(v, hars.nets.tce.state_dict()[k]) for k, v in tce_before.items())  # ψ kept
    assert any(not torch.equal(v, hars.nets.fab.state_dict()[k]) for k, v in fab_before.items())  # ϕ fresh
    assert list(hars.phi_names) == [f.name for f in program.factors if f.type == "PHI"]


def test_halfcheetah_velocity_factor_is_gated_on_posture_after_decoupling(tmp_path: Path) -> None:
    hars, held = _train_hars("halfcheetah", episodes=40, length=300, on_back_every=2, updates=2000)
    phi = hars.potential(held["obs"]).numpy()
    pvc = d_pvc(phi, held["value"])
    assert pvc < 0.3  # the velocity-driven potential pays the cheetah on its back like the running one
    healthy = {"peg": -1e-5, "tpd": 0.1, "pvc": 0.7, "fap": 0.01, "rpe": 0.4}
    result = _diagnose({"pvc": pvc}, healthy, returns=(100.0, 60.0))
    assert result.contributors[0].metric == "pvc" and result.gradient["pvc"] > 0
    assert "decoupled" in result.contributors[0].reading

    decision = _reframe(tmp_path, "halfcheetah", hars, held, result, recent=60.0, band=None)
    assert decision.accepted, decision.reason
    assert decision.operators == ["Gate"]
    (edit,) = decision.program.edits
    assert edit["targets"] == ["r_vel"] and edit["params"]["posture_feature"] == "pitch"
    gated = next(f for f in decision.program.factors if f.name == "r_vel")
    assert "s.pitch" in gated.code and "s.x_velocity" in gated.code
    verdicts = json.loads((tmp_path / "iv" / "candidates.json").read_text())
    chosen = verdicts[decision.candidate]["verdicts"]["efficacy"]
    assert chosen["auc"] > 0.5 and chosen["auc_p"] < 0.05 and chosen["j_srr"] > 0
    assert (tmp_path / "iv" / "accepted.diff").read_text().count("s.pitch") >= 1
    _install_and_check_reinit(hars, "halfcheetah", decision.program)


def test_humanoidstandup_escape_bonus_is_added_at_the_stagnation_band(tmp_path: Path) -> None:
    hars, held = _train_hars("humanoidstandup", episodes=40, length=300, on_back_every=None, updates=1000)
    card = load_task("humanoidstandup")
    phi_s = hars.potential(held["obs"]).numpy()
    phi_next = hars.potential(held["next_obs"]).numpy() * (1.0 - held["terminal"])
    rpe = d_rpe(phi_s, held["r"], phi_next, GAMMA, held["terminal"])
    # The potential leaves much of the TD target unexplained: a residual plateau, far above a learning
    # run's (the healthy phase below). Its exact value after a fixed number of updates moves with float
    # rounding (0.3-0.55 over implementations of the same networks), hence the margin.
    assert rpe > 0.3
    heights = card.feature_values(held["obs"])["torso_height"]
    center, half = stagnation_band(heights)
    assert float(np.median(heights)) < 0.3  # lying on the floor, far below standing height (~1.3 m)
    healthy = {"peg": -1e-5, "tpd": 0.1, "pvc": 0.5, "fap": 0.01, "rpe": 0.15}
    plateau = 5000.0
    result = _diagnose({"rpe": rpe, "peg": -5e-5}, healthy, returns=(plateau - 14, plateau + 5))
    assert "rpe" in [c.metric for c in result.contributors] and result.gradient["rpe"] < 0

    band = {"feature": "torso_height", "center": center, "halfwidth": half}
    decision = _reframe(tmp_path, "humanoidstandup", hars, held, result, recent=plateau + 5, band=band)
    assert decision.accepted, decision.reason
    assert decision.operators == ["Add"]
    (edit,) = decision.program.edits
    added = next(f for f in decision.program.factors if f.name == edit["params"]["new_factor"])
    assert added.type == "PHI"  # state-only: it becomes part of the potential, never reads the action
    assert "s.torso_height" in added.code and "s.z_velocity" in added.code
    assert edit["params"]["z_stag"] == pytest.approx(center, abs=1e-3)
    _install_and_check_reinit(hars, "humanoidstandup", decision.program)
