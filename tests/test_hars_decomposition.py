"""HARS's decomposition head: r̂ fitted to episodic returns, the reward Φ is aligned to and the agent learns from."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mira.replay import ReplayBuffer
from mira.rewards.decomposition import EpisodeSumRegression
from mira.shaping import decomposition
from mira.shaping.config import HarsConfig
from mira.shaping.decomposition import DecompositionHead
from mira.shaping.factors import FunctionFactorSource
from mira.shaping.source import HarsReward
from mira.shaping.testing import make_hars

OBS, ACT = 4, 2


def _factors() -> FunctionFactorSource:
    return FunctionFactorSource(
        {"speed": lambda o: o[:, 0], "lean": lambda o: -np.square(o[:, 1]), "noise": lambda o: np.sin(3 * o[:, 2])},
        {"effort": lambda o, a: -np.sum(a * a, axis=-1)})


def _true_reward(next_obs: np.ndarray, act: np.ndarray) -> np.ndarray:
    """Linear in the factors at s′ and (s, a): 2·speed(s′) + 0.5·effort + 0.3, nothing from ``lean``/``noise``."""
    return 2.0 * next_obs[:, 0] - 0.5 * np.sum(act * act, axis=-1) + 0.3


def _feed(src: HarsReward, buf: ReplayBuffer, episodes: int, rng: np.random.Generator, dense: str = "nan"
          ) -> None:
    """Episodes of random length whose per-step reward is :func:`_true_reward`; the buffer's dense column
    holds NaN (or the truth), the agent-visible reward is episodic."""
    for _ in range(episodes):
        n = int(rng.integers(20, 60))
        obs = rng.normal(size=(n + 1, OBS)).astype(np.float32)
        obs[:, 0] += rng.normal()  # episodes differ in their mean speed, as policies do
        act = rng.uniform(-1, 1, (n, ACT)).astype(np.float32)
        rew = _true_reward(obs[1:].astype(np.float64), act.astype(np.float64))
        total = float(rew.sum())
        ep = int(buf.episode_id[buf.pos - 1]) + 1 if buf.size else 0
        for t in range(n):
            last = t == n - 1
            dense_t = float("nan") if dense == "nan" else float(rew[t])
            row = buf.add(obs[t], act[t], total if last else 0.0, dense_t, obs[t + 1], False, last, ep)
            src.on_transition(row)
        src.on_episode_end(buf.finish_episode(total), total)


def test_episode_sum_regression_recovers_a_linear_per_step_reward() -> None:
    rng = np.random.default_rng(0)
    theta = np.array([1.5, -0.7, 0.2, 0.05])
    reg = EpisodeSumRegression(4, ridge=1e-6)
    for _ in range(200):
        n = int(rng.integers(10, 80))
        x = np.concatenate([rng.normal(rng.normal(), 1.0, (n, 3)), np.ones((n, 1))], axis=1)
        reg.add(x.sum(0), float((x @ theta).sum()), n)
    np.testing.assert_allclose(reg.fit(), theta, atol=1e-4)
    assert reg.r2 == pytest.approx(1.0, abs=1e-8)


def test_selected_ridge_keeps_a_large_mean_small_spread_factor_at_its_weight() -> None:
    """Returns paying ``v − c`` per step, where the cost ``c`` is large on every step, varies little
    between episodes and moves with the speed (a control cost), on episodes of one length (so the bias
    is a constant column): a fixed ridge of one pseudo-episode shrinks the near-collinear weights against
    the evidence and turns the cost into a bonus; the ridge chosen by leave-one-out recovers the reward."""
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(100):
        speed = rng.uniform(0.0, 5.0)
        v = speed + rng.normal(0.0, 1.0, 1000)
        c = 0.4 + 0.02 * speed + rng.normal(0.0, 0.05, 1000)
        rows.append((np.array([v.sum(), -c.sum(), 1000.0]), float((v - c).sum())))
    fits = {}
    for select in (False, True):
        reg = EpisodeSumRegression(3, ridge=1.0, centred=True, select=select)
        for x, ret in rows:
            reg.add(x, ret, 1000.0)
        fits[select] = reg.fit()
        if select:
            assert reg.chosen_ridge < 1e-2
    np.testing.assert_allclose(fits[True], [1.0, 1.0, 0.0], atol=0.05)
    assert fits[False][1] < 0.5  # a fixed ridge: the cost's weight pulled far from 1
    few = EpisodeSumRegression(3, ridge=1.0, centred=True, select=True)
    for x, ret in rows[:3]:
        few.add(x, ret, 1000.0)
    few.fit()
    assert np.all(np.isfinite(few.theta))
    head = DecompositionHead(["v"], ["c"])
    assert head.regression.select and head.regression.centred  # the head's: the ridge the evidence chooses


def test_head_recovers_the_per_step_reward_from_episode_sums_without_reading_the_dense_reward(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(decomposition, "DECOMPOSE_RIDGE", 1e-6)
    src, buf = make_hars(_factors(), obs_dim=OBS, act_dim=ACT, capacity=8_000,
                         config=HarsConfig(shaping_weight=0.0))
    rng = np.random.default_rng(1)
    _feed(src, buf, 80, rng, dense="nan")
    w = dict(zip(src.head.names, src.head.weights, strict=True))
    assert w["speed"] == pytest.approx(2.0, abs=1e-3)
    assert w["effort"] == pytest.approx(0.5, abs=1e-3)
    assert w["bias"] == pytest.approx(0.3, abs=1e-3)
    assert abs(w["lean"]) < 1e-3 and abs(w["noise"]) < 1e-3
    batch = buf.sample(256, rng)
    truth = _true_reward(batch.next_obs.numpy().astype(np.float64), batch.action.numpy().astype(np.float64))
    reward = src.relabel(batch)  # κ = 0 here: the agent's reward is r̂ itself
    assert torch.isfinite(reward).all()
    np.testing.assert_allclose(reward.detach().numpy(), truth, atol=1e-2)
    # ... and the raw-array path the outer loop uses gives the same numbers.
    np.testing.assert_allclose(
        src.decomposed_reward(batch.obs.numpy(), batch.action.numpy(), batch.next_obs.numpy()), truth, atol=1e-2)
    metrics = src.update(batch, 0)
    assert set(metrics) == set(src.log_fields)
    assert all(torch.isfinite(v) for v in metrics.values())  # NaN dense column: nothing read it
    assert float(metrics["decomp_r2"]) == pytest.approx(1.0, abs=1e-6)
    assert float(metrics["share_speed"]) > float(metrics["share_lean"])


def test_head_reads_phi_factors_at_s_next_and_explains_a_reward_earned_over_the_step() -> None:
    """The reward is a function of s′: the head, which reads PHI factors there, explains the returns."""
    src, buf = make_hars(_factors(), obs_dim=OBS, act_dim=ACT, capacity=8_000)
    _feed(src, buf, 60, np.random.default_rng(2))
    assert src.head.regression.r2 > 0.999


def test_alignment_target_is_r_hat_and_phi_gets_no_dense_or_episodic_signal() -> None:
    """Φ's TD target is r̂ + γ(1 − d)Φ(s′) under decomposed alignment, r_ext + ... under episodic."""
    for alignment in ("decomposed", "episodic"):
        src, buf = make_hars(_factors(), obs_dim=OBS, act_dim=ACT, capacity=4_000,
                             config=HarsConfig(alignment=alignment))
        rng = np.random.default_rng(3)
        _feed(src, buf, 10, rng)
        batch = buf.sample(64, rng)
        with torch.enable_grad():
            reward = src.relabel(batch)
        pending = src._pending
        assert pending is not None
        rows = torch.from_numpy(batch.indices)
        expected_base = batch.reward if alignment == "episodic" else src.decomposed.of_rows(rows)
        assert torch.equal(pending.base, expected_base)
        b = batch.reward.shape[0]
        phi = pending.phi.detach()
        pbrs = src.gamma * (1.0 - batch.terminated) * phi[b:] - phi[:b]
        torch.testing.assert_close(reward.detach(), expected_base + src.kappa * pbrs)
        assert src.kappa == (1.0 if alignment == "episodic" else 0.0)  # the defaults


def test_kappa_adds_the_pbrs_term_in_grouped_and_single_relabelling() -> None:
    src, buf = make_hars(_factors(), obs_dim=OBS, act_dim=ACT, capacity=4_000,
                         config=HarsConfig(shaping_weight=0.5), background=False)
    rng = np.random.default_rng(4)
    _feed(src, buf, 10, rng)
    for step in range(3):  # land a few training steps so Φ is not at its initial weights
        batch = buf.sample(32, rng)
        src.relabel(batch)
        src.update(batch, step)
    src.sync()
    batches = [buf.sample(32, rng) for _ in range(3)]
    with torch.no_grad():
        grouped = [r if isinstance(r, torch.Tensor) else r.result() for r in src._shape_frozen(batches)]
    for batch, reward in zip(batches, grouped, strict=True):
        rows = torch.from_numpy(batch.indices)
        phi_s, phi_n = src.potential(batch.obs), src.potential(batch.next_obs)
        expected = src.decomposed.of_rows(rows) + 0.5 * (src.gamma * (1.0 - batch.terminated) * phi_n - phi_s)
        torch.testing.assert_close(reward, expected, rtol=1e-5, atol=1e-5)


def test_head_state_survives_a_checkpoint_bit_for_bit_and_a_new_program_refits_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(decomposition, "DECOMPOSE_RIDGE", 1e-6)
    config = HarsConfig()
    src, buf = make_hars(_factors(), obs_dim=OBS, act_dim=ACT, capacity=4_000, config=config)
    rng = np.random.default_rng(5)
    _feed(src, buf, 12, rng)
    state = src.state_dict()
    clone = HarsReward(_factors(), config)
    clone.bind(src.ctx)
    clone.load_state_dict(state)
    assert np.array_equal(clone.head.weights, src.head.weights)
    assert np.array_equal(clone.head.regression.sums[:12], src.head.regression.sums[:12])
    batch = buf.sample(64, rng)
    assert torch.equal(clone.relabel(batch), src.relabel(batch))
    _feed(src, buf, 1, np.random.default_rng(6))
    # A program without ``noise``: the head is refitted on the stored episodes, with the new features.
    smaller = FunctionFactorSource({"speed": lambda o: o[:, 0]}, {"effort": lambda o, a: -np.sum(a * a, axis=-1)})
    src.set_program(smaller)
    assert src.head.names == ["speed", "effort", "bias"]
    assert src.head.regression.count == 13
    w = dict(zip(src.head.names, src.head.weights, strict=True))
    assert w["speed"] == pytest.approx(2.0, abs=1e-3)


def test_on_a_task_whose_return_is_made_of_the_factors_pvc_is_positive_and_the_program_ranks_states() -> None:
    """What MCM and SRR read once HARS has learned: the value labels are the return-to-go of r̂ along
    rollouts (not γ^(T−t)·R), Φ aligned to r̂ correlates with them (PVC > 0) and the current program's
    proxy potential ranks held-out states by them (AUC > 0.5)."""
    from mira.loop.rollout import discounted_return_to_go
    from mira.mcm.metrics import d_pvc
    from mira.srr.efficacy import proxy_efficacy

    src, buf = make_hars(_factors(), obs_dim=OBS, act_dim=ACT, capacity=20_000,
                         config=HarsConfig(update_every=1, lr=1e-3), background=False)
    rng = np.random.default_rng(7)

    def rollout(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """A Markov chain: speed persists (AR(1)), so a state's value depends on its own speed."""
        obs = np.zeros((n + 1, OBS), dtype=np.float32)
        obs[0] = rng.normal(size=OBS)
        for t in range(n):
            obs[t + 1] = 0.9 * obs[t] + 0.45 * rng.normal(size=OBS)
        act = rng.uniform(-1, 1, (n, ACT)).astype(np.float32)
        return obs, act, _true_reward(obs[1:].astype(np.float64), act.astype(np.float64)), 0.0

    for _ in range(30):
        obs, act, rew, _ = rollout(100)
        total = float(rew.sum())
        ep = int(buf.episode_id[buf.pos - 1]) + 1 if buf.size else 0
        for t in range(100):
            last = t == 99
            row = buf.add(obs[t], act[t], total if last else 0.0, float("nan"), obs[t + 1], False, last, ep)
            src.on_transition(row)
        src.on_episode_end(buf.finish_episode(total), total)
    for step in range(400):
        batch = buf.sample(128, rng)
        src.relabel(batch)
        src.update(batch, step)
    # Held-out episodes, as the outer loop collects them.
    parts = [rollout(100) for _ in range(4)]
    obs = np.concatenate([p[0][:-1] for p in parts])
    next_obs = np.concatenate([p[0][1:] for p in parts])
    act = np.concatenate([p[1] for p in parts])
    episode = np.repeat(np.arange(4), 100)
    values = discounted_return_to_go(src.decomposed_reward(obs, act, next_obs), episode, src.gamma)
    keep = np.concatenate([np.arange(k * 100, k * 100 + 50) for k in range(4)])  # away from the truncation
    phi = src.potential(obs[keep]).numpy().astype(np.float64)
    assert d_pvc(phi, values[keep]) > 0.3
    eff = proxy_efficacy(src.proxy_potential(src.factors, obs[keep]).numpy(), values[keep], n_perm=200)
    assert eff.auc > 0.5 and eff.auc_p < 0.05
