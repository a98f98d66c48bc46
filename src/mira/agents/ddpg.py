"""Deep Deterministic Policy Gradient (Lillicrap et al., 2016) with Gaussian action noise."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch

from mira.agents.base import AgentConfig, PolicyStats
from mira.agents.networks import DeterministicActor, EnsembleQ, make_adam, polyak_update
from mira.replay import Batch


class DDPG:
    algo = "ddpg"

    def __init__(self, obs_dim: int, act_dim: int, config: AgentConfig, device: torch.device) -> None:
        self.config = config
        self.device = device
        self.act_dim = act_dim
        self.actor = DeterministicActor(obs_dim, act_dim, config.hidden).to(device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic = EnsembleQ(1, obs_dim, act_dim, config.hidden).to(device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_opt = make_adam(list(self.actor.parameters()), config.lr)
        self.critic_opt = make_adam(list(self.critic.parameters()), config.lr)
        self.updates = 0
        # Exploration noise comes from torch's generator so one seed fixes the whole run.
        self._noise_std = config.exploration_noise

    @torch.inference_mode()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
        action = self.actor(x)[0]
        if not deterministic:
            action = (action + self._noise_std * torch.randn_like(action)).clamp(-1.0, 1.0)
        return action.cpu().numpy()

    def update(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        cfg = self.config
        with torch.no_grad():
            q_next = self.critic_target(batch.next_obs, self.actor_target(batch.next_obs))[0]
        target = reward + cfg.gamma * (1.0 - batch.terminated) * q_next
        q = self.critic(batch.obs, batch.action)[0]
        critic_loss = (q - target).pow(2).mean()
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        metrics = {"critic_loss": critic_loss.detach(), "q_mean": q.detach().mean()}
        if self.updates % cfg.policy_delay:
            return metrics

        self.critic.requires_grad_(False)
        actor_loss = -self.critic(batch.obs, self.actor(batch.obs))[0].mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        self.critic.requires_grad_(True)
        polyak_update(self.actor, self.actor_target, cfg.tau)
        polyak_update(self.critic, self.critic_target, cfg.tau)
        metrics["actor_loss"] = actor_loss.detach()
        return metrics

    @torch.no_grad()
    def policy_stats(self, obs: torch.Tensor) -> PolicyStats:
        mean = self.actor(obs.to(self.device)).cpu().numpy()
        log_std = np.full_like(mean, math.log(max(self._noise_std, 1e-6)))
        return PolicyStats(mean, log_std, squashed=False)

    @torch.no_grad()
    def value(self, obs: torch.Tensor) -> torch.Tensor:
        obs = obs.to(self.device)
        return self.critic(obs, self.actor(obs))[0]

    def actor_state(self) -> dict[str, torch.Tensor]:
        """A frozen copy of the policy's parameters (the monitor's snapshot of this cycle's policy)."""
        return {k: v.detach().clone() for k, v in self.actor.state_dict().items()}

    @torch.no_grad()
    def policy_stats_with(self, actor_state: dict[str, torch.Tensor], obs: torch.Tensor) -> PolicyStats:
        """Policy statistics (Gaussian surrogate) of a snapshot taken by :meth:`actor_state` on ``obs``."""
        mean = torch.func.functional_call(self.actor, actor_state, (obs.to(self.device),)).cpu().numpy()
        log_std = np.full_like(mean, math.log(max(self._noise_std, 1e-6)))
        return PolicyStats(mean, log_std, squashed=False)

    def state_dict(self) -> dict[str, Any]:
        return {
            "actor": self.actor.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.actor_target.load_state_dict(state["actor_target"])
        self.critic.load_state_dict(state["critic"])
        self.critic_target.load_state_dict(state["critic_target"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = state["updates"]
