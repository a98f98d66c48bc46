"""Deep Deterministic Policy Gradient (Lillicrap et al., 2016) with Gaussian action noise.

As for SAC, ``AgentConfig.kernels`` chooses between :meth:`DDPG.update_plain` (autograd, the
reference) and :meth:`DDPG.update_fused` (explicit backward formulas on reused buffers and fused Adam,
the default); the same update up to float rounding (``tests/test_agents.py``).
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch

from mira.agents.base import AgentConfig, PolicyStats
from mira.agents.networks import (
    AdamStepper,
    DeterministicActor,
    EnsembleQ,
    EnsembleQKernels,
    MLPKernels,
    make_adam,
    relu_mlp_1d,
)
from mira.agents.torch_private import foreach_lerp_
from mira.replay import Batch


class DDPG:
    algo = "ddpg"

    def __init__(self, obs_dim: int, act_dim: int, config: AgentConfig, device: torch.device) -> None:
        self.config = config
        self.device = device
        self.obs_dim = obs_dim
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
        self._q_kernels = EnsembleQKernels(self.critic)
        self._pi_kernels = MLPKernels(self.actor.params())
        self._critic_step = AdamStepper(self.critic_opt)
        self._actor_step = AdamStepper(self.actor_opt)
        self._bind_params()

    def _bind_params(self) -> None:
        self._actor_params = self.actor.params()
        self._critic_params = self.critic.params()
        self._actor_target_params = self.actor_target.params()
        self._critic_target_params = self.critic_target.params()
        self._actor_grads = [torch.zeros_like(p) for p in self._actor_params]
        self._critic_grads = [torch.zeros_like(p) for p in self._critic_params]
        self._online = self._actor_params + self._critic_params
        self._targets = self._actor_target_params + self._critic_target_params

    @torch.inference_mode()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        action = torch.tanh(relu_mlp_1d(self._actor_params, x))
        if not deterministic:
            action = (action + self._noise_std * torch.randn_like(action)).clamp_(-1.0, 1.0)
        return action.cpu().numpy()

    def update(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        if self.config.kernels == "plain":
            return self.update_plain(batch, reward)
        return self.update_fused(batch, reward)

    def update_plain(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        """One DDPG update with autograd: the reference :meth:`update_fused` computes faster."""
        cfg = self.config
        obs = batch.obs
        with torch.no_grad():
            next_action = self.actor_target(batch.next_obs)
            q_next = self.critic_target(batch.next_obs, next_action)[0]
        target = reward + cfg.gamma * (1.0 - batch.terminated) * q_next  # the reward may carry gradient
        q = self.critic(obs, batch.action)
        critic_loss = (q[0] - target).square().mean()
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        metrics = {"critic_loss": critic_loss.detach(), "q_mean": q.detach().mean()}

        # Actor: maximise Q(s, π(s)) through the updated critic, which gets no gradient from this loss.
        q_pi = self.critic(obs, self.actor(obs), params=[p.detach() for p in self.critic.params()])[0]
        actor_loss = -q_pi.mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        with torch.no_grad():
            for target_p, p in zip(self._targets, self._online, strict=True):
                target_p.lerp_(p, cfg.tau)
        metrics["actor_loss"] = actor_loss.detach()
        return metrics

    def update_fused(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        """One DDPG update through the explicit-backward kernels and fused Adam; the same update as
        :meth:`update_plain` up to float rounding."""
        cfg = self.config
        q_k, pi_k = self._q_kernels, self._pi_kernels
        critic, actor = self._critic_params, self._actor_params
        obs = batch.obs
        n = obs.shape[0]
        with torch.no_grad():
            next_action = torch.tanh(pi_k.forward(self._actor_target_params, batch.next_obs))
            q_next = q_k.forward(self._critic_target_params, torch.cat((batch.next_obs, next_action), -1))[0]
            target = reward.detach() + cfg.gamma * (1.0 - batch.terminated) * q_next
            # Loss: mean squared TD error; dL/dq = 2 (q - target) / B.
            q = q_k.forward(critic, torch.cat((obs, batch.action), -1))
            q_mean = q.mean()
            td = q - target
            critic_loss = td.square().mean()
            dq = td.mul_(2.0 / n)
            q_k.backward(critic, dq, self._critic_grads)
            for p, g in zip(critic, self._critic_grads, strict=True):
                p.grad = g
        if reward.requires_grad:
            reward.backward(dq[0].neg())  # dL/dtarget, for a reward that carries gradients
        self._critic_step.step()
        self.updates += 1
        metrics = {"critic_loss": critic_loss, "q_mean": q_mean}

        with torch.no_grad():
            # Actor: maximise Q(s, pi(s)); the critic gets no gradient from this loss.
            action = torch.tanh(pi_k.forward(actor, obs))
            actor_loss = q_k.forward(critic, torch.cat((obs, action), -1))[0].mean().neg()
            d_action = q_k.input_grad_of_min(critic, None, -1.0 / n, slice(self.obs_dim, None))
            g_out = torch.addcmul(d_action, d_action, action.square(), value=-1.0)  # through tanh
            pi_k.backward(actor, g_out, self._actor_grads)
            for p, g in zip(actor, self._actor_grads, strict=True):
                p.grad = g
        self._actor_step.step()
        with torch.no_grad():
            foreach_lerp_(self._targets, self._online, cfg.tau)
        metrics["actor_loss"] = actor_loss
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
        self._bind_params()
