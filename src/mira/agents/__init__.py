"""Off-policy agents: SAC and DDPG, sharing networks and the replay buffer."""

from __future__ import annotations

import dataclasses
import logging

import torch

from mira.agents.base import Agent, AgentConfig, PolicyStats
from mira.agents.ddpg import DDPG
from mira.agents.sac import SAC
from mira.agents.torch_private import fused_path_problem

ALGOS = ("sac", "ddpg")
KERNELS = ("fused", "plain")


def make_agent(algo: str, obs_dim: int, act_dim: int, config: AgentConfig, device: torch.device) -> Agent:
    """Build the agent named by ``algo`` (``sac`` or ``ddpg``); the fused update falls back to the plain one
    where this PyTorch cannot run it (:func:`~mira.agents.torch_private.fused_path_problem`)."""
    if config.kernels not in KERNELS:
        raise ValueError(f"agent.kernels must be one of {', '.join(KERNELS)}, not {config.kernels!r}")
    if config.kernels == "fused" and (problem := fused_path_problem()) is not None:
        # The fused path calls PyTorch internals (mira.agents.torch_private); on a PyTorch where one is
        # missing or changed, the plain autograd update computes the same thing, more slowly.
        logging.getLogger(__name__).warning("the fused agent update cannot run on PyTorch %s (%s): using the plain "
                                            "autograd update", torch.__version__, problem)
        config = dataclasses.replace(config, kernels="plain")
    if algo == "sac":
        return SAC(obs_dim, act_dim, config, device)
    if algo == "ddpg":
        return DDPG(obs_dim, act_dim, config, device)
    raise ValueError(f"unknown algo {algo!r} (choose from {', '.join(ALGOS)})")


__all__ = ["ALGOS", "DDPG", "KERNELS", "SAC", "Agent", "AgentConfig", "PolicyStats", "make_agent"]
