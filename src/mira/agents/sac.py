"""Soft Actor-Critic (Haarnoja et al., 2018) with twin critics and a learned temperature.

The critics are one ensemble module (one batched matmul per layer for both). The reward used in the
critic target is whatever the reward source gave: for HARS it may carry gradients into the potential,
which is how the critic loss reaches (phi, varphi) in the joint objective; SAC itself only steps its
own optimisers.

Two ways to compute an update, chosen by ``AgentConfig.kernels``: :meth:`SAC.update_plain` is the
algorithm with autograd, on one screen; :meth:`SAC.update_fused` (the default) runs the networks
through :class:`~mira.agents.networks.EnsembleQKernels` and :class:`~mira.agents.networks.MLPKernels`
(explicit backward formulas on reused buffers) and steps the optimisers in one fused Adam call. The
arithmetic, the order of the random draws and the result are the same up to float rounding
(``tests/test_agents.py``); the fused path exists for speed.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch

from mira.agents.base import AgentConfig, PolicyStats
from mira.agents.networks import (
    _LOG_STD_HALF,
    _LOG_STD_MID,
    AdamStepper,
    EnsembleQ,
    EnsembleQKernels,
    MLPKernels,
    SquashedGaussianActor,
    make_adam,
    relu_mlp_1d,
    squashed_gaussian_backward,
    squashed_gaussian_forward,
)
from mira.agents.torch_private import foreach_lerp_
from mira.replay import Batch


class SAC:
    algo = "sac"

    def __init__(self, obs_dim: int, act_dim: int, config: AgentConfig, device: torch.device) -> None:
        self.config = config
        self.device = device
        self.obs_dim = obs_dim
        self.act_dim = act_dim
        self.actor = SquashedGaussianActor(obs_dim, act_dim, config.hidden).to(device)
        self.critic = EnsembleQ(2, obs_dim, act_dim, config.hidden).to(device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(config.init_alpha), device=device, requires_grad=True)
        self.target_entropy = -float(act_dim) if config.target_entropy is None else float(config.target_entropy)
        self.actor_opt = make_adam(list(self.actor.parameters()), config.lr)
        self.critic_opt = make_adam(list(self.critic.parameters()), config.lr)
        self.alpha_opt = make_adam([self.log_alpha], config.lr)
        self.updates = 0
        self._q_kernels = EnsembleQKernels(self.critic)
        self._pi_kernels = MLPKernels(self.actor.params())
        self._critic_step = AdamStepper(self.critic_opt)
        self._actor_step = AdamStepper(self.actor_opt)
        self._actor_alpha_step = AdamStepper(self.actor_opt, self.alpha_opt)
        self._bind_params()

    def _bind_params(self) -> None:
        self._critic_params = self.critic.params()
        self._target_params = self.critic_target.params()
        self._critic_grads = [torch.zeros_like(p) for p in self._critic_params]
        self._actor_params = self.actor.params()
        self._actor_grads = [torch.zeros_like(p) for p in self._actor_params]

    @torch.inference_mode()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        # actor.sample / actor.deterministic without the log-probability (same draws, same action).
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        mean, raw = relu_mlp_1d(self._actor_params, x).chunk(2)
        if deterministic:
            return torch.tanh(mean).cpu().numpy()
        std = torch.tanh(raw).mul_(_LOG_STD_HALF).add_(_LOG_STD_MID).exp_()
        return torch.tanh(torch.addcmul(mean, std, torch.randn_like(mean))).cpu().numpy()

    def update(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        if self.config.kernels == "plain":
            return self.update_plain(batch, reward)
        return self.update_fused(batch, reward)

    def update_plain(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        """One SAC update with autograd: the reference :meth:`update_fused` computes faster."""
        cfg = self.config
        obs, n = batch.obs, batch.obs.shape[0]
        alpha = self.log_alpha.detach().exp()
        # The standard normal draws, in the fused path's order: the target's, then the actor loss's.
        noise_next = torch.randn(n, self.act_dim, dtype=obs.dtype, device=obs.device)
        noise_pi = torch.randn(n, self.act_dim, dtype=obs.dtype, device=obs.device)

        # Critic: soft Bellman target from the target critics; truncation is not a terminal. The reward
        # may carry gradient (HARS's joint objective): the critic loss then reaches it through the target.
        with torch.no_grad():
            next_action, next_logp = self.actor.sample_with(batch.next_obs, noise_next)
            q_next = self.critic_target(batch.next_obs, next_action).min(0).values - alpha * next_logp
        target = reward + cfg.gamma * (1.0 - batch.terminated) * q_next
        q = self.critic(obs, batch.action)
        critic_loss = (q - target).square().mean(1).sum()
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        metrics = {"critic_loss": critic_loss.detach(), "q_mean": q.detach().mean(), "alpha": alpha}

        # Actor: maximise min-Q minus alpha log-prob on the updated critics (detached: no gradient to them).
        action, logp = self.actor.sample_with(obs, noise_pi)
        q_pi = self.critic(obs, action, params=[p.detach() for p in self.critic.params()]).min(0).values
        actor_loss = (alpha * logp - q_pi).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        if cfg.autotune_alpha:
            alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_opt.step()
        with torch.no_grad():
            for target_p, p in zip(self.critic_target.parameters(), self.critic.parameters(), strict=True):
                target_p.lerp_(p, cfg.tau)
        metrics.update(actor_loss=actor_loss.detach(), entropy=-logp.detach().mean())
        return metrics

    def update_fused(self, batch: Batch, reward: torch.Tensor) -> dict[str, torch.Tensor]:
        """One SAC update through the explicit-backward kernels and one fused Adam call (see the module
        docstring); the same update as :meth:`update_plain` up to float rounding."""
        cfg = self.config
        q_k, pi_k = self._q_kernels, self._pi_kernels
        critic, actor = self._critic_params, self._actor_params
        obs = batch.obs
        n = obs.shape[0]
        alpha = self.log_alpha.detach().exp()

        # The actor's forward pass on next_obs (target) and on obs (actor loss) is one pass over both: the
        # actor does not change in between, and the noise is drawn in the same order as two separate
        # samples would draw it.
        with torch.no_grad():
            # Critic: soft Bellman target from the target critics; truncation is not a terminal.
            noise = torch.randn(n, self.act_dim, dtype=obs.dtype, device=obs.device)
            noise = torch.cat((noise, torch.randn(n, self.act_dim, dtype=obs.dtype, device=obs.device)))
            pi_in = torch.cat((batch.next_obs, obs))
            both_action, both_logp, saved = squashed_gaussian_forward(pi_k.forward(actor, pi_in), noise)
            next_action, next_logp = both_action[:n], both_logp[:n]
            q_next = q_k.forward(self._target_params, torch.cat((batch.next_obs, next_action), -1))
            q_next = q_next.min(0).values - alpha * next_logp
            target = reward.detach() + cfg.gamma * (1.0 - batch.terminated) * q_next
            # Loss: sum over critics of the mean squared TD error; dL/dq = 2 (q - target) / B.
            q = q_k.forward(critic, torch.cat((obs, batch.action), -1))
            q_mean = q.mean()
            td = q - target
            critic_loss = td.square().mean(1).sum()
            dq = td.mul_(2.0 / n)
            q_k.backward(critic, dq, self._critic_grads)
            for p, g in zip(critic, self._critic_grads, strict=True):
                p.grad = g
        if reward.requires_grad:
            # The target's reward term gets dL/dtarget = -sum_e dL/dq_e (HARS's joint objective).
            reward.backward(dq.sum(0).neg_())
        self._critic_step.step()
        self.updates += 1
        metrics = {"critic_loss": critic_loss, "q_mean": q_mean, "alpha": alpha}

        with torch.no_grad():
            # Actor: maximise min-Q minus alpha log-prob, on the freshly updated critics, which get no
            # gradient from this loss (only dL/daction is propagated through them).
            action, logp = both_action[n:], both_logp[n:]
            saved = tuple(t[n:] for t in saved)
            q_pi = q_k.forward(critic, torch.cat((obs, action), -1))
            q_min, argmin = q_pi.min(0)
            actor_loss = (alpha * logp - q_min).mean()
            d_action = q_k.input_grad_of_min(critic, argmin, -1.0 / n, slice(self.obs_dim, None))
            pi_k.backward(actor, squashed_gaussian_backward(saved, d_action, alpha / n), self._actor_grads,
                          slice(n, None))
            for p, g in zip(actor, self._actor_grads, strict=True):
                p.grad = g
            if cfg.autotune_alpha:
                # d/d log_alpha of -mean(log_alpha * (logp + target_entropy)).
                self.log_alpha.grad = (logp + self.target_entropy).mean().neg_()
        if cfg.autotune_alpha:
            self._actor_alpha_step.step()  # actor and temperature in one fused Adam call
        else:
            self._actor_step.step()
        with torch.no_grad():
            foreach_lerp_(self._target_params, critic, cfg.tau)
        metrics.update(actor_loss=actor_loss, entropy=-logp.mean())
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
        self._bind_params()
