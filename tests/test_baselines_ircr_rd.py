"""IRCR's credits and RD's least-squares fit on synthetic problems with known per-step rewards."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mira.baselines.config import IRCRConfig, RDConfig
from mira.baselines.ircr import IRCRReward
from mira.baselines.rd import RDReward, feature_dim, linear_features
from mira.baselines.synthetic import SyntheticEpisodes, linear_reward
from mira.replay import ReplayBuffer
from mira.rewards.base import RewardContext, RewardSource
from mira.tasks.card import load_task

OBS, ACT = 3, 2


def _bind(source: RewardSource, capacity: int = 50_000, obs_dim: int = OBS, act_dim: int = ACT) -> ReplayBuffer:
    buf = ReplayBuffer(capacity, obs_dim, act_dim)
    source.bind(RewardContext(load_task("halfcheetah"), obs_dim, act_dim, 0.99, torch.device("cpu"), buf, 0,
                              Path(".")))
    return buf


# ----------------------------------------------------------------------------------------- IRCR


def test_ircr_credits_are_in_unit_interval_and_ordered_like_per_step_returns() -> None:
    src = IRCRReward()
    assert src.needs_complete_episodes
    buf = _bind(src)
    gen = SyntheticEpisodes(OBS, ACT, lambda o, a: o[:, 0] + a[:, 0], seed=3)  # lengths 20-60
    gen.feed(buf, src, 30)
    per_step = src.store.returns / src.store.length
    assert (src.r_min, src.r_max) == (per_step.min(), per_step.max())
    batch = buf.sample(2000, np.random.default_rng(0), completed_only=True)
    credit = src.relabel(batch).numpy()
    lengths = np.bincount(buf.episode_id[: buf.size].numpy())[batch.episode_id.numpy()]
    ret = batch.episode_return.numpy() / lengths
    assert credit.min() >= 0.0 and credit.max() <= 1.0
    order = np.argsort(ret, kind="stable")
    assert np.all(np.diff(credit[order]) >= -1e-6)  # monotone in the trajectory's return
    assert credit[ret == ret.min()].max() == pytest.approx(0.0, abs=1e-6)
    assert credit[ret == ret.max()].min() == pytest.approx(1.0, abs=1e-6)
    # Uniform credit: every transition of an episode gets the same value.
    for ep in np.unique(batch.episode_id.numpy())[:5]:
        assert np.ptp(credit[batch.episode_id.numpy() == ep]) == 0.0
    metrics = src.update(batch, 1)
    assert set(metrics) == set(IRCRReward.log_fields)
    assert all(v.dim() == 0 for v in metrics.values())


def test_ircr_equal_returns_give_the_configured_constant() -> None:
    src = IRCRReward(IRCRConfig(equal_credit=0.5))
    buf = _bind(src)
    SyntheticEpisodes(OBS, ACT, lambda o, a: np.zeros(len(o)), seed=0).feed(buf, src, 3)
    batch = buf.sample(64, np.random.default_rng(0), completed_only=True)
    assert torch.all(src.relabel(batch) == 0.5)


def test_ircr_min_max_follow_the_ring_buffer() -> None:
    src = IRCRReward()
    buf = _bind(src, capacity=200)
    gen = SyntheticEpisodes(OBS, ACT, lambda o, a: np.ones(len(o)), min_len=50, max_len=50, seed=0)
    gen.feed(buf, src, 2)  # returns 50, 50
    gen.reward_fn = lambda o, a: 2 * np.ones(len(o))
    gen.feed(buf, src, 4)  # per-step returns 2: the first two episodes are overwritten
    assert src.r_min == src.r_max == 2.0
    state = src.state_dict()
    clone = IRCRReward()
    clone.bind(src.ctx)
    clone.load_state_dict(state)
    assert (clone.r_min, clone.r_max) == (2.0, 2.0)
    assert np.array_equal(clone.heap_first, src.heap_first) and clone.heap_first.size == 4


def test_ircr_keeps_a_heap_of_the_best_trajectories_and_draws_half_of_each_batch_from_it() -> None:
    src = IRCRReward(IRCRConfig(heap_episodes=3, heap_fraction=0.5))
    buf = _bind(src)
    gen = SyntheticEpisodes(OBS, ACT, lambda o, a: o[:, 0] + a[:, 0], seed=5)
    gen.feed(buf, src, 40)
    per_step = src.store.returns / src.store.length
    best = np.sort(per_step)[-3:]
    np.testing.assert_allclose(np.sort(src.heap_score), best)
    rows = src.sample_rows(256, np.random.default_rng(0))
    assert rows.shape == (256,)
    heap_ep = {int(buf.episode_id[int(f % buf.capacity)]) for f in src.heap_first}
    from_heap = np.isin(buf.episode_id[torch.from_numpy(rows)].numpy(), list(heap_ep))
    assert from_heap[128:].all()  # the second half comes from the heap
    assert from_heap[:128].mean() < 0.5  # the first half is uniform over 40 episodes
    credit = src.relabel(buf.gather(rows)).numpy()
    assert credit[128:].mean() > credit[:128].mean()


# ------------------------------------------------------------------------------------------- RD


def test_rd_recovers_linear_reward_weights() -> None:
    rng = np.random.default_rng(7)
    w_true = rng.normal(size=feature_dim(OBS, ACT))
    src = RDReward(RDConfig(ridge=1e-6, refit_every_episodes=10, min_episodes=20))
    buf = _bind(src)
    SyntheticEpisodes(OBS, ACT, linear_reward(w_true), seed=11).feed(buf, src, 200)
    assert src.fits > 0
    theta = src.fit()
    np.testing.assert_allclose(theta, w_true, atol=1e-3)
    assert float(src.update(buf.sample(8, rng, True), 1)["rd_loss"]) < 1e-8
    batch = buf.sample(256, rng, completed_only=True)
    expected = linear_features(batch.obs.double(), batch.action.double()).numpy() @ w_true
    np.testing.assert_allclose(src.relabel(batch).numpy(), expected, rtol=1e-3, atol=1e-3)


def test_rd_is_zero_before_min_episodes_and_bounded_after() -> None:
    src = RDReward(RDConfig(min_episodes=5, max_episodes=8))
    buf = _bind(src)
    gen = SyntheticEpisodes(OBS, ACT, linear_reward(np.ones(feature_dim(OBS, ACT))), seed=0)
    gen.feed(buf, src, 4)
    batch = buf.sample(32, np.random.default_rng(0), completed_only=True)
    assert torch.all(src.relabel(batch) == 0.0)
    assert "rd_loss" not in src.update(batch, 0)  # no fit yet: nothing (not a NaN the trainer would stop on)
    gen.feed(buf, src, 20)
    assert src.regression.count == 8 and src.fits > 0
    assert torch.isfinite(src.relabel(batch)).all()
    clone = RDReward(RDConfig(min_episodes=5, max_episodes=8))
    clone.bind(src.ctx)
    clone.load_state_dict(src.state_dict())
    assert torch.equal(clone.relabel(batch), src.relabel(batch))
    np.testing.assert_allclose(clone.fit(), src.fit())
