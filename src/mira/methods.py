"""From a method name to the reward source and outer-loop hooks it trains with.

This is the only place that knows every method; the trainer only sees a ``RewardSource`` and a list
of hooks. Builders import their modules lazily so that a plain ``dense`` run loads no LLM or MCM code.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mira.config import TrainConfig
from mira.loop.hooks import CycleHook
from mira.rewards.base import DenseReward, RewardSource, SparseReward
from mira.tasks.card import TaskCard


@dataclass
class MethodParts:
    reward: RewardSource
    hooks: list[CycleHook]
    description: str


MethodBuilder = Callable[[TrainConfig, TaskCard, Path], MethodParts]


def _dense(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    return MethodParts(DenseReward(), [], "oracle: the environment's dense per-step reward")


def _sparse(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    return MethodParts(SparseReward(), [], "episodic reward only (return at the episode's last step)")


METHODS: dict[str, MethodBuilder] = {
    "dense": _dense,
    "sparse": _sparse,
}


def build_method(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    return METHODS[config.method](config, card, run_dir)
