"""RD — return decomposition with a linear reward, after Efroni, Merlis and Mannor (2021),
"Reinforcement Learning with Trajectory Feedback".

Definition (their section 4): with trajectory feedback only the return R(τ) = Σ_t r(s_t, a_t) (+ noise)
is observed. Assuming a linear reward r(s, a) = φ(s, a)ᵀθ, the return is linear in the trajectory's
summed features, R(τ) = Φ(τ)ᵀθ with Φ(τ) = Σ_t φ(s_t, a_t), so θ is estimated by regularised least
squares over the trajectories seen so far: θ̂ = (Σ_τ ΦΦᵀ + λI)⁻¹ Σ_τ Φ R. The agent then optimises
the estimated per-step reward φ(s, a)ᵀθ̂.

Ours:

* **Feature map** ``φ(s, a) = [s, a, a², 1]`` (dimension ``obs_dim + 2·act_dim + 1``): the raw
  observation, the action, its element-wise square and a bias. It is cheap (no parameters, summed
  once per episode) and it can express the usual MuJoCo rewards — linear progress terms (forward
  velocity, torso height) and quadratic control costs — while anything non-linear in s is beyond it,
  which is exactly the limitation of a linear-reward baseline.
* **Ridge in standardised units** (:class:`~mira.rewards.decomposition.EpisodeSumRegression`, shared
  with HARS's decomposition head): the penalty is ``ridge · diag(ΦᵀΦ)/n`` instead of ``λI``, so raw
  observation entries of very different magnitudes are shrunk alike.
* **No optimism**: Efroni et al. add a UCB / Thompson-sampling bonus from the regression's
  confidence set to explore; here the agent's own exploration (SAC's entropy, DDPG's noise) is
  used, as for every other method in the comparison.
* **Bounded memory**: only each episode's summed features, return and length are kept (at most
  ``max_episodes``), never its transitions; the fit is recomputed every ``refit_every_episodes``.
  Episodes not wholly in the replay buffer when they end (longer than its capacity) are skipped.
* The logged fit loss ``rd_loss`` is the mean squared per-step residual ((R − Φᵀθ̂)/T)² over the
  stored episodes; the reward is 0 until ``min_episodes`` episodes are stored.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from mira.baselines.common import TrajectoryRewardSource
from mira.baselines.config import RDConfig
from mira.replay import Batch
from mira.rewards.base import RewardContext
from mira.rewards.decomposition import EpisodeSumRegression


def linear_features(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """φ(s, a) = [s, a, a², 1] for a batch: ``[N, obs_dim + 2·act_dim + 1]``."""
    ones = torch.ones((obs.shape[0], 1), dtype=obs.dtype, device=obs.device)
    return torch.cat((obs, action, action * action, ones), dim=1)


def feature_dim(obs_dim: int, act_dim: int) -> int:
    return obs_dim + 2 * act_dim + 1


class RDReward(TrajectoryRewardSource):
    """Per-step reward φ(s, a)ᵀθ̂ with θ̂ from ridge regression of returns on summed episode features."""

    name = "rd"
    log_fields: ClassVar[tuple[str, ...]] = ("rd_loss", "corr_dense")

    def __init__(self, config: RDConfig | None = None) -> None:
        self.config = config or RDConfig()
        cfg = self.config
        if cfg.refit_every_episodes <= 0 or cfg.min_episodes <= 0 or cfg.max_episodes <= 0:
            raise ValueError("rd: refit_every_episodes, min_episodes and max_episodes must be positive")
        if cfg.ridge < 0:
            raise ValueError("rd: ridge must be >= 0")
        super().__init__(max_episodes=cfg.max_episodes)

    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        d = feature_dim(ctx.obs_dim, ctx.act_dim)
        self.dim = d
        self.regression = EpisodeSumRegression(d, ridge=self.config.ridge, max_episodes=self.config.max_episodes)
        self.since_fit = 0
        self.theta = torch.zeros(d, dtype=torch.float32, device=ctx.device)
        self._loss = torch.tensor(float("nan"))

    @property
    def fits(self) -> int:
        return self.regression.fits

    # ----------------------------------------------------------------------------- data and fit
    def episode_added(self, index: int, rows: np.ndarray, episode_return: float) -> None:
        buf = self.ctx.buffer
        idx = torch.from_numpy(np.asarray(rows, dtype=np.int64))
        phi = linear_features(buf.obs[idx].double(), buf.action[idx].double()).sum(0).numpy()
        self.regression.add(phi, episode_return, float(len(rows)))
        self.since_fit += 1
        if self.since_fit >= self.config.refit_every_episodes and self.regression.count >= self.config.min_episodes:
            self.fit()

    def fit(self) -> np.ndarray:
        """Solve the ridge problem on every stored episode; returns θ̂ (float64)."""
        theta = self.regression.fit()
        self._loss = torch.tensor(self.regression.loss)
        self.theta = torch.as_tensor(theta, dtype=torch.float32, device=self.ctx.device)
        self.since_fit = 0
        return theta

    # ------------------------------------------------------------------------------------ reward
    def reward_of(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return linear_features(obs, action) @ self.theta.to(obs.device)

    def compute_reward(self, batch: Batch) -> torch.Tensor:
        return self.reward_of(batch.obs, batch.action)

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        # No fit yet (fewer than min_episodes finished): no loss to report, rather than a NaN that would
        # read as a diverged run.
        out = {"rd_loss": self._loss} if self.fits else {}
        out.update(self.diagnostics(batch))
        return out

    def describe(self) -> dict[str, Any]:
        return {"method": self.name, "features": "[s, a, a^2, 1]", "ridge": self.config.ridge,
                "refit_every_episodes": self.config.refit_every_episodes,
                "max_episodes": self.config.max_episodes}

    def state_dict(self) -> dict[str, Any]:
        return {**self.base_state(), "regression": self.regression.state_dict(), "since_fit": self.since_fit,
                "theta": self.theta.cpu(), "loss": self._loss}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_base_state(state)
        self.regression.load_state_dict(state["regression"])
        self.since_fit = int(state["since_fit"])
        self.theta = state["theta"].to(self.ctx.device, torch.float32)
        self._loss = state["loss"]
