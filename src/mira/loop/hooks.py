"""The explicit interface through which outer loops (MIRA's monitor and reframer) observe training.

A hook runs every ``interval`` environment steps and receives a :class:`CycleContext`: the objects it
may read (agent, buffer, reward source) and a function to roll out held-out episodes with the
current, frozen policy. It never sees the loop's locals. Its whole state is checkpointed with the run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from mira.agents.base import Agent
from mira.loop.evaluation import EvalResult
from mira.loop.rollout import Rollout
from mira.replay import ReplayBuffer
from mira.rewards.base import RewardSource
from mira.runio.rundir import RunDir


@dataclass
class CycleContext:
    step: int
    agent: Agent
    buffer: ReplayBuffer
    reward: RewardSource
    run: RunDir
    last_eval: EvalResult | None
    rollout: Callable[[int, int], Rollout]
    """``rollout(episodes, seed_base)``: held-out episodes with the current policy, deterministic."""


class CycleHook(Protocol):
    interval: int

    def on_cycle(self, ctx: CycleContext) -> dict[str, float]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...

    def on_fork(self, run: RunDir, program: Any | None) -> None:
        """A fork (``mira train --fork``) starts here from its parent's state; ``program``, when given, is the
        factor program to install now (``--fork-program``)."""
        ...
