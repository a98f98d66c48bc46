"""What a method builder hands the trainer."""

from __future__ import annotations

from dataclasses import dataclass

from mira.loop.hooks import CycleHook
from mira.rewards.base import RewardSource


@dataclass
class MethodParts:
    """A method, built: the reward source the agent learns from, the hooks that run every cycle (MIRA's
    outer loop), and one line saying what it is (recorded in ``config.json``, shown by ``mira explain``)."""

    reward: RewardSource
    hooks: list[CycleHook]
    description: str
