"""Held-out rollouts handed to outer loops."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rollout:
    """Held-out episodes collected with a frozen policy snapshot (for diagnostics)."""

    obs: np.ndarray
    next_obs: np.ndarray
    actions: np.ndarray
    r_ext: np.ndarray
    """Extrinsic (episodic) reward of each step: 0 except at an episode's last step."""
    terminated: np.ndarray
    episode_index: np.ndarray
    returns: np.ndarray
    """Each episode's extrinsic return."""


def discounted_return_to_go(rewards: np.ndarray, episode_index: np.ndarray, gamma: float) -> np.ndarray:
    """``Σ_{k≥t} γ^(k−t) r_k`` within each episode (episodes laid end to end, as in :class:`Rollout`)."""
    rewards = np.asarray(rewards, dtype=np.float64)
    out = np.zeros_like(rewards)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        if t == len(rewards) - 1 or episode_index[t] != episode_index[t + 1]:
            running = 0.0
        running = rewards[t] + gamma * running
        out[t] = running
    return out
