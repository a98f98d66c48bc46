"""Soft Actor-Critic (Haarnoja et al., 2018) with twin critics and a learned temperature.

The critics are one ensemble module (one batched matmul per layer for both). The reward used in the
critic target is whatever the reward source gave: for HARS it may carry gradients into the potential,
which is how the critic loss reaches (phi, varphi) in the joint objective; SAC itself only steps its
own optimisers.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from mira.agents.base import AgentConfig, PolicyStats
from mira.agents.networks import AdamStepper, EnsembleQ, SquashedGaussianActor, make_adam, polyak_update
from mira.replay import Batch


class SAC:
    algo = "sac"

    def __init__(self, obs_dim: int, act_dim: int, config: AgentConfig, device: torch.device) -> None:
        self.config = config
        self.device = device
        self.act_dim = act_dim
        self.actor = SquashedGaussianActor(obs_dim, act_dim, config.hidden).to(device)
        self.critic = EnsembleQ(2, obs_dim, act_dim, config.hidden).to(device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(config.init_alpha), device=device, requires_grad=True)
        self.target_entropy = -float(act_dim)
        self.actor_opt = make_adam(list(self.actor.parameters()), config.lr)
        self.critic_opt = make_adam(list(self.critic.parameters()), config.lr)
        self.alpha_opt = make_adam([self.log_alpha], config.lr)
        self._critic_step = AdamStepper(self.critic_opt)
        self._actor_step = AdamStepper(self.actor_opt)
        self._actor_alpha_step = AdamStepper(self.actor_opt, self.alpha_opt)
        self.updates = 0

    @torch.inference_mode()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
        action = self.actor.deterministic(x) if deterministic else self.actor.sample(x)[0]
        return action[0].cpu().numpy()

    def update(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        cfg = self.config
        alpha = self.log_alpha.detach().exp()
        critic_params = self.critic.params()

        # Critic: soft Bellman target from the target critics; truncation is not a terminal.
        with torch.no_grad():
            next_action, next_logp = self.actor.sample(batch.next_obs)
            q_next = self.critic_target(batch.next_obs, next_action).min(0).values - alpha * next_logp
            bootstrap = cfg.gamma * (1.0 - batch.terminated) * q_next
        # Outside no_grad: a reward that requires grad (HARS's joint mode) gets the critic loss's gradient.
        target = reward + bootstrap
        q = self.critic(batch.obs, batch.action, critic_params)
        # sum over critics of the mean squared TD error (mse_loss sums [E, B], then / B).
        critic_loss = F.mse_loss(q, target.expand_as(q), reduction="sum") / q.shape[1]
        self._critic_step.zero_grad()
        critic_loss.backward()
        self._critic_step.step()
        self.updates += 1
        metrics = {"critic_loss": critic_loss.detach(), "q_mean": q.detach().mean(), "alpha": alpha}
        if self.updates % cfg.policy_delay:
            return metrics

        # Actor: maximise min-Q minus alpha log-prob; the critics run on detached parameters, so this
        # loss gives them no gradient (and the freshly updated critics are used, as before).
        action, logp = self.actor.sample(batch.obs)
        q_pi = self.critic(batch.obs, action, [p.detach() for p in critic_params]).min(0).values
        actor_loss = (alpha * logp - q_pi).mean()
        self._actor_step.zero_grad()
        actor_loss.backward()
        if cfg.autotune_alpha:
            # d/d log_alpha of -mean(log_alpha * (logp + target_entropy)), without a backward pass.
            with torch.no_grad():
                self.log_alpha.grad = (logp.detach() + self.target_entropy).mean().neg_()
            self._actor_alpha_step.step()  # actor and temperature in one fused Adam call
        else:
            self._actor_step.step()
        polyak_update(self.critic, self.critic_target, cfg.tau)
        metrics.update(actor_loss=actor_loss.detach(), entropy=-logp.detach().mean())
        return metrics

    @torch.no_grad()
    def policy_stats(self, obs: torch.Tensor) -> PolicyStats:
        mean, log_std = self.actor.distribution(obs.to(self.device))
        return PolicyStats(mean.cpu().numpy(), log_std.cpu().numpy(), squashed=True)

    @torch.no_grad()
    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """Critic estimate of the state value under the current (deterministic) policy."""
        obs = obs.to(self.device)
        return self.critic(obs, self.actor.deterministic(obs)).min(0).values

    def actor_state(self) -> dict[str, torch.Tensor]:
        """A frozen copy of the policy's parameters (the monitor's snapshot of this cycle's policy)."""
        return {k: v.detach().clone() for k, v in self.actor.state_dict().items()}

    @torch.no_grad()
    def policy_stats_with(self, actor_state: dict[str, torch.Tensor], obs: torch.Tensor) -> PolicyStats:
        """Policy statistics of a snapshot taken by :meth:`actor_state` on ``obs``."""
        mean, log_std = torch.func.functional_call(self.actor, actor_state, (obs.to(self.device),))
        return PolicyStats(mean.cpu().numpy(), log_std.cpu().numpy(), squashed=True)

    def state_dict(self) -> dict[str, Any]:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.critic_target.load_state_dict(state["critic_target"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.updates = state["updates"]
