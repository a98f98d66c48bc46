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
    dense_rewards: np.ndarray
    terminated: np.ndarray
    episode_index: np.ndarray
    returns: np.ndarray
    mc_values: np.ndarray
    """Discounted Monte-Carlo return-to-go of each state (V̂_ext under the frozen policy)."""
