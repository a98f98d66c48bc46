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
    mc_values: np.ndarray
    """Discounted episodic return-to-go of each state (Monte-Carlo V̂_ext under the frozen policy)."""
