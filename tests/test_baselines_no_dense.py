"""No baseline reads the hidden dense reward for its reward: NaN in the dense column leaves rewards
finite, and random dense values leave them unchanged (only the logged ``corr_dense`` may differ)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mira.baselines.config import IRCRConfig, LaReConfig, RDConfig, VIBConfig
from mira.baselines.ircr import IRCRReward
from mira.baselines.lare import LaReReward
from mira.baselines.rd import RDReward
from mira.baselines.synthetic import SyntheticEpisodes
from mira.baselines.vib import VIBReward
from mira.replay import ReplayBuffer
from mira.rewards.base import RewardContext, RewardSource
from mira.tasks.card import load_task

OBS, ACT = 5, 3


class Factors:
    @property
    def names(self) -> list[str]:
        return ["f0", "f1", "f2"]

    def phi(self, obs: np.ndarray) -> np.ndarray:
        return np.stack((obs[:, 0], np.tanh(obs[:, 1])), axis=1)

    def aux(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        return -np.sum(action * action, axis=1, keepdims=True)


def _make(method: str) -> RewardSource:
    small = {"hidden": (16, 16), "episodes_per_batch": 3, "subseq_len": 8}
    if method == "ircr":
        return IRCRReward(IRCRConfig())
    if method == "rd":
        return RDReward(RDConfig(min_episodes=2))
    if method == "vib":
        return VIBReward(VIBConfig(**small, latent_dim=4))  # type: ignore[arg-type]
    return LaReReward(Factors(), LaReConfig(**small))  # type: ignore[arg-type]


def _run(method: str, dense: str) -> tuple[list[torch.Tensor], list[dict[str, torch.Tensor]]]:
    torch.manual_seed(0)
    source = _make(method)
    buf = ReplayBuffer(2_000, OBS, ACT)
    source.bind(RewardContext(load_task("halfcheetah"), OBS, ACT, 0.99, torch.device("cpu"), buf, 0, Path(".")))
    gen = SyntheticEpisodes(OBS, ACT, lambda o, a: o[:, 0] - 0.1 * (a * a).sum(1), min_len=15, max_len=40,
                            seed=4, dense=dense)
    rng = np.random.default_rng(0)
    rewards, metrics = [], []
    for step in range(1, 61):
        if step % 10 == 1:
            gen.feed(buf, source, 2)
        batch = buf.sample(32, rng, completed_only=source.needs_complete_episodes)
        rewards.append(source.relabel(batch).detach().clone())
        metrics.append(source.update(batch, step))
    if dense == "nan":
        assert torch.isnan(buf.dense_reward[: buf.size]).all()
    return rewards, metrics


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("method", ["ircr", "rd", "vib", "lare"])
def test_rewards_do_not_depend_on_the_dense_column(method: str) -> None:
    nan_rewards, nan_metrics = _run(method, "nan")
    rnd_rewards, rnd_metrics = _run(method, "random")
    true_rewards, true_metrics = _run(method, "true")
    for a, b, c in zip(nan_rewards, rnd_rewards, true_rewards, strict=True):
        assert torch.isfinite(a).all()
        assert torch.equal(a, b) and torch.equal(a, c)
    for m_nan, m_rnd in zip(nan_metrics, rnd_metrics, strict=True):
        assert set(m_nan) == set(m_rnd)
        for key in m_nan:
            if key == "corr_dense":
                continue
            assert torch.equal(m_nan[key], m_rnd[key]) or (m_nan[key].isnan() and m_rnd[key].isnan())
    assert torch.isnan(nan_metrics[-1]["corr_dense"])  # the diagnostic does read the column...
    assert torch.isfinite(true_metrics[-1]["corr_dense"])  # ...and only the diagnostic
    assert all(v.dim() == 0 for v in true_metrics[-1].values())
