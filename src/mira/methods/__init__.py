"""From a method name to the reward source and outer-loop hooks it trains with.

This is the only place that knows every method; the trainer only sees a ``RewardSource`` and a list
of hooks. Builders import their modules lazily so that a plain ``dense`` run loads no LLM or MCM code.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mira.config import TrainConfig
from mira.methods.parts import MethodParts
from mira.rewards.base import DenseReward, SparseReward
from mira.tasks.card import TaskCard

MethodBuilder = Callable[[TrainConfig, TaskCard, Path], MethodParts]


def _dense(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    return MethodParts(DenseReward(), [], "oracle: the environment's dense per-step reward")


def _sparse(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    return MethodParts(SparseReward(), [], "episodic reward only (return at the episode's last step)")


def _hars(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    from mira.methods.hars import build_hars

    return build_hars(config, card, run_dir)


def _baseline(method: str) -> MethodBuilder:
    def build(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
        from mira.methods.baselines import build_baseline

        reward, description = build_baseline(method, config, card, run_dir)
        return MethodParts(reward, [], description)

    return build


def _mira(method: str) -> MethodBuilder:
    def build(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
        from mira.methods.mira import build_mira

        parts: MethodParts = build_mira(config, card, run_dir, method)
        return parts

    return build


METHODS: dict[str, MethodBuilder] = {
    "mira": _mira("mira"),
    "mira-no-mcm": _mira("mira-no-mcm"),
    "mira-no-srr": _mira("mira-no-srr"),
    "dense": _dense,
    "sparse": _sparse,
    "hars": _hars,
    "lare": _baseline("lare"),
    "rd": _baseline("rd"),
    "ircr": _baseline("ircr"),
    "vib": _baseline("vib"),
}


FORK_FAMILIES: tuple[frozenset[str], ...] = (frozenset({"mira", "mira-no-mcm", "mira-no-srr"}),)
"""Methods whose checkpoints load into one another (the same reward source and outer loop, in other modes):
a fork (``mira train --fork``) may switch between them, e.g. continue a ``mira`` run with SRR off."""


def fork_compatible(parent: str, method: str) -> bool:
    """Whether a checkpoint of a ``parent`` run can continue as ``method``."""
    return parent == method or any(parent in family and method in family for family in FORK_FAMILIES)


def build_method(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    return METHODS[config.method](config, card, run_dir)
