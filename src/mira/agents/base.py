"""What the trainer and the monitor need from an agent."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from mira.replay import Batch


@dataclass
class AgentConfig:
    """Hyperparameters shared by SAC and DDPG (the field's usual values; ``--preset paper``: Table 1)."""

    lr: float = 3e-4
    """Learning rate of actor, critics (and SAC's temperature): 3e-4 as in SB3 and CleanRL (Table 1:
    1e-4, with which HalfCheetah has not started to run by 50k steps, ours and SB3's SAC alike)."""
    gamma: float = 0.99
    """Discount factor; Table 1."""
    hidden: tuple[int, ...] = (256, 256)
    """Hidden widths of the actor and critic MLPs (ReLU); Table 1."""
    batch_size: int = 256
    """Minibatch size per gradient step."""
    tau: float = 0.005
    """Polyak factor of the target networks."""
    init_alpha: float = 1.0
    """SAC: initial entropy temperature."""
    autotune_alpha: bool = True
    """SAC: learn the temperature towards ``target_entropy``."""
    target_entropy: float | None = None
    """SAC: the policy entropy (nats) the temperature is tuned towards; None: -|A|, SB3's and CleanRL's
    ``auto``. Higher keeps the policy more random for longer (a fork may change it: it decides no network)."""
    exploration_noise: float = 0.1
    """DDPG: std of the Gaussian action noise (actions in [-1, 1])."""
    kernels: str = "fused"
    """How an update is computed: ``fused`` (explicit backward formulas on reused buffers and one fused
    Adam call, see :mod:`mira.agents.networks`: the fast path) or ``plain`` (autograd and the optimisers'
    own ``step()``: the reference, readable top to bottom). The same update up to float rounding
    (``tests/test_agents.py`` checks they agree)."""


@dataclass
class PolicyStats:
    """The policy's action distribution on a set of states, for the monitor.

    SAC: mean and log-std of the pre-tanh Gaussian (``squashed=True``). DDPG: the deterministic action
    and the log of the exploration noise std (its Gaussian surrogate, ``squashed=False``).
    """

    mean: np.ndarray
    log_std: np.ndarray
    squashed: bool


class Agent(Protocol):
    """An off-policy actor-critic agent driven by the trainer."""

    algo: str

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray: ...

    def update(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]: ...

    def policy_stats(self, obs: torch.Tensor) -> PolicyStats: ...

    def value(self, obs: torch.Tensor) -> torch.Tensor: ...

    def actor_state(self) -> dict[str, torch.Tensor]: ...

    def policy_stats_with(self, actor_state: dict[str, torch.Tensor], obs: torch.Tensor) -> PolicyStats: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...
