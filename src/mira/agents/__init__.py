"""Off-policy agents: SAC and DDPG, sharing networks and the replay buffer."""

from __future__ import annotations

import torch

from mira.agents.base import Agent, AgentConfig, PolicyStats
from mira.agents.ddpg import DDPG
from mira.agents.sac import SAC

ALGOS = ("sac", "ddpg")
KERNELS = ("fused", "plain")


def make_agent(algo: str, obs_dim: int, act_dim: int, config: AgentConfig, device: torch.device) -> Agent:
    """Build the agent named by ``algo`` (``sac`` or ``ddpg``)."""
    if config.kernels not in KERNELS:
        raise ValueError(f"agent.kernels must be one of {', '.join(KERNELS)}, not {config.kernels!r}")
    if algo == "sac":
        return SAC(obs_dim, act_dim, config, device)
    if algo == "ddpg":
        return DDPG(obs_dim, act_dim, config, device)
    raise ValueError(f"unknown algo {algo!r} (choose from {', '.join(ALGOS)})")


__all__ = ["ALGOS", "DDPG", "KERNELS", "SAC", "Agent", "AgentConfig", "PolicyStats", "make_agent"]
