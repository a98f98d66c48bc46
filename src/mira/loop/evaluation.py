"""Evaluation: the extrinsic episodic return of the deterministic policy on a separate environment.

Each evaluation uses the same episode seeds (``seed_base + k``), so evaluations are comparable across
steps and need no environment state in a checkpoint. Shaping never enters the figure: it is the sum
of the environment's own dense reward.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mira.agents.base import Agent
from mira.loop.rollout import Rollout
from mira.tasks.envs import EpisodicRewardWrapper


@dataclass
class EvalResult:
    returns: np.ndarray
    lengths: np.ndarray

    @property
    def mean(self) -> float:
        return float(self.returns.mean())

    @property
    def std(self) -> float:
        return float(self.returns.std())


def evaluate(agent: Agent | Any, env: EpisodicRewardWrapper, episodes: int, seed_base: int) -> EvalResult:
    """``episodes`` deterministic episodes of anything with ``act(obs, deterministic=True)`` (an agent
    while training, a loaded policy file afterwards), from seeds ``seed_base + k``."""
    returns, lengths = [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed_base + k)
        total, length, done = 0.0, 0, False
        while not done:
            obs, _, terminated, truncated, info = env.step(agent.act(obs, deterministic=True))
            total += info["dense_reward"]
            length += 1
            done = terminated or truncated
        returns.append(total)
        lengths.append(length)
    return EvalResult(np.asarray(returns), np.asarray(lengths))


def collect_rollout(agent: Agent, env: EpisodicRewardWrapper, episodes: int, seed_base: int) -> Rollout:
    """Held-out episodes of the deterministic policy.

    Only the extrinsic, *episodic* reward enters: ``r_ext`` is 0 except at each episode's last step.
    The dense per-step reward is not recorded, so nothing downstream can use it.
    """
    obs_l, next_l, act_l, rext_l, term_l, ep_l, returns = [], [], [], [], [], [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed_base + k)
        done, length = False, 0
        while not done:
            action = agent.act(obs, deterministic=True)
            next_obs, r_ext, terminated, truncated, info = env.step(action)
            obs_l.append(obs)
            next_l.append(next_obs)
            act_l.append(action)
            rext_l.append(float(r_ext))
            term_l.append(terminated)
            ep_l.append(k)
            obs = next_obs
            length += 1
            done = terminated or truncated
        returns.append(float(info["episode_return"]))
    return Rollout(
        obs=np.asarray(obs_l, dtype=np.float32),
        next_obs=np.asarray(next_l, dtype=np.float32),
        actions=np.asarray(act_l, dtype=np.float32),
        r_ext=np.asarray(rext_l),
        terminated=np.asarray(term_l, dtype=bool),
        episode_index=np.asarray(ep_l),
        returns=np.asarray(returns),
    )
