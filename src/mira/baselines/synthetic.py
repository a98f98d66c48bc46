"""Synthetic trajectory-feedback problems with a known per-step reward, to check a baseline alone.

Episodes of random observations and actions are written to a :class:`~mira.replay.ReplayBuffer`
exactly as the trainer writes them (episodic reward: 0 except the return at the last step; the
per-step reward in the ``dense_reward`` column) and reported to a reward source through
``on_transition`` / ``on_episode_end``. Whether a baseline recovers the per-step reward from the
returns alone can then be measured against the known truth. Used by the test suite.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mira.replay import ReplayBuffer
from mira.rewards.base import RewardSource

RewardFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class SyntheticEpisodes:
    """Random episodes whose per-step reward is ``reward_fn(obs, action)``.

    Observations are standard normal, actions uniform in [-1, 1]; lengths are drawn uniformly from
    ``[min_len, max_len]`` (variable lengths make a constant reward term identifiable from returns).
    """

    obs_dim: int
    act_dim: int
    reward_fn: RewardFn
    min_len: int = 20
    max_len: int = 60
    seed: int = 0
    dense: str = "true"
    """What the buffer's ``dense_reward`` column receives: ``true`` (the per-step reward), ``nan`` or
    ``random`` (to show a method never reads it)."""

    def __post_init__(self) -> None:
        if self.dense not in ("true", "nan", "random"):
            raise ValueError(f"dense must be 'true', 'nan' or 'random', not {self.dense!r}")
        self.rng = np.random.default_rng(self.seed)
        self.noise = np.random.default_rng(self.seed + 1)  # separate stream: episodes do not depend on it
        self.episodes = 0

    def episode(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One episode: observations ``[T+1, obs_dim]``, actions ``[T, act_dim]``, rewards ``[T]``, terminal flags."""
        length = int(self.rng.integers(self.min_len, self.max_len + 1))
        obs = self.rng.standard_normal((length + 1, self.obs_dim))
        act = self.rng.uniform(-1.0, 1.0, (length, self.act_dim))
        rew = np.asarray(self.reward_fn(obs[:-1], act), dtype=np.float64).reshape(length)
        done = np.zeros(length, dtype=bool)
        done[-1] = True
        return obs, act, rew, done

    def feed(self, buffer: ReplayBuffer, source: RewardSource | None = None, episodes: int = 1) -> list[float]:
        """Write ``episodes`` episodes to ``buffer`` and report them to ``source``; returns their returns."""
        returns: list[float] = []
        for _ in range(episodes):
            obs, act, rew, done = self.episode()
            total = float(rew.sum())
            if self.dense == "nan":
                dense = np.full_like(rew, np.nan)
            elif self.dense == "random":
                dense = self.noise.normal(0.0, 100.0, rew.shape)
            else:
                dense = rew
            for t in range(len(rew)):
                last = bool(done[t])
                row = buffer.add(obs[t], act[t], total if last else 0.0, float(dense[t]), obs[t + 1],
                                 False, last, self.episodes)
                if source is not None:
                    source.on_transition(row)
            rows = buffer.finish_episode(total)
            if source is not None:
                source.on_episode_end(rows, total)
            self.episodes += 1
            returns.append(total)
        return returns


def linear_reward(weights: np.ndarray) -> RewardFn:
    """The reward ``[s, a, a², 1] · weights`` (the feature map of :mod:`mira.baselines.rd`)."""
    w = np.asarray(weights, dtype=np.float64)

    def fn(obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        phi = np.concatenate((obs, action, action * action, np.ones((obs.shape[0], 1))), axis=1)
        return phi @ w

    return fn
