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
* **Ridge in standardised units**: the penalty is ``ridge · diag(ΦᵀΦ)/n`` instead of ``λI``, i.e.
  ridge regression on summed features rescaled to unit mean square, so raw observation entries of
  very different magnitudes are shrunk alike; ``ridge = 1`` weighs like one pseudo-episode pulling
  every weight to zero and washes out as episodes accumulate. A tiny absolute jitter keeps the
  system solvable when a feature is identically zero.
* **No optimism**: Efroni et al. add a UCB / Thompson-sampling bonus from the regression's
  confidence set to explore; here the agent's own exploration (SAC's entropy, DDPG's noise) is
  used, as for every other method in the comparison.
* **Bounded memory**: only each episode's summed features, return and length are kept (O(d) per
  episode, at most ``max_episodes``, oldest dropped), never its transitions; the fit is recomputed
  from them every ``refit_every_episodes`` episodes. Episodes not wholly in the replay buffer when
  they end (longer than its capacity) are skipped.
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

    def __init__(self, config: RDConfig | None = None, *, log_corr_dense: bool = True) -> None:
        self.config = config or RDConfig()
        cfg = self.config
        if cfg.refit_every_episodes <= 0 or cfg.min_episodes <= 0 or cfg.max_episodes <= 0:
            raise ValueError("rd: refit_every_episodes, min_episodes and max_episodes must be positive")
        if cfg.ridge < 0:
            raise ValueError("rd: ridge must be >= 0")
        super().__init__(max_episodes=cfg.max_episodes, log_corr_dense=log_corr_dense)

    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        d = feature_dim(ctx.obs_dim, ctx.act_dim)
        self.dim = d
        self.sums = np.zeros((0, d), dtype=np.float64)  # ring of per-episode summed features
        self.returns = np.zeros(0, dtype=np.float64)
        self.lengths = np.zeros(0, dtype=np.float64)
        self.count = 0  # episodes held (<= max_episodes)
        self.head = 0  # next slot once the ring is full
        self.since_fit = 0
        self.fits = 0
        self.theta = torch.zeros(d, dtype=torch.float32, device=ctx.device)
        self._loss = torch.tensor(float("nan"))

    # ----------------------------------------------------------------------------- data and fit
    def episode_added(self, index: int, rows: np.ndarray, episode_return: float) -> None:
        buf = self.ctx.buffer
        idx = torch.from_numpy(np.asarray(rows, dtype=np.int64))
        phi = linear_features(buf.obs[idx].double(), buf.action[idx].double()).sum(0).numpy()
        self._append(phi, episode_return, float(len(rows)))
        self.since_fit += 1
        if self.since_fit >= self.config.refit_every_episodes and self.count >= self.config.min_episodes:
            self.fit()

    def _append(self, phi: np.ndarray, ret: float, length: float) -> None:
        cap = self.config.max_episodes
        if self.count < cap:
            if self.count == self.sums.shape[0]:  # grow geometrically up to the cap
                new = min(cap, max(16, 2 * self.sums.shape[0]))
                self.sums = np.concatenate((self.sums, np.zeros((new - self.count, self.dim))))
                self.returns = np.concatenate((self.returns, np.zeros(new - self.count)))
                self.lengths = np.concatenate((self.lengths, np.zeros(new - self.count)))
            slot = self.count
            self.count += 1
        else:
            slot = self.head
            self.head = (self.head + 1) % cap
        self.sums[slot], self.returns[slot], self.lengths[slot] = phi, ret, length

    def fit(self) -> np.ndarray:
        """Solve the ridge problem on every stored episode; returns θ̂ (float64)."""
        n = self.count
        F, R, T = self.sums[:n], self.returns[:n], self.lengths[:n]
        A = F.T @ F
        b = F.T @ R
        diag = np.diag(A).copy()
        jitter = 1e-10 * max(float(diag.mean()), 1e-12)
        A_reg = A + np.diag(self.config.ridge * diag / n + jitter)
        try:
            theta = np.linalg.solve(A_reg, b)
        except np.linalg.LinAlgError:
            theta = np.linalg.lstsq(A_reg, b, rcond=None)[0]
        if not np.all(np.isfinite(theta)):
            theta = np.zeros_like(theta)
        resid = (R - F @ theta) / np.maximum(T, 1.0)
        self._loss = torch.tensor(float(np.mean(resid**2)))
        self.theta = torch.as_tensor(theta, dtype=torch.float32, device=self.ctx.device)
        self.since_fit = 0
        self.fits += 1
        return theta

    # ------------------------------------------------------------------------------------ reward
    def reward_of(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return linear_features(obs, action) @ self.theta.to(obs.device)

    def compute_reward(self, batch: Batch) -> torch.Tensor:
        return self.reward_of(batch.obs, batch.action)

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        out = {"rd_loss": self._loss}
        out.update(self.diagnostics(batch))
        return out

    def describe(self) -> dict[str, Any]:
        return {"method": self.name, "features": "[s, a, a^2, 1]", "ridge": self.config.ridge,
                "refit_every_episodes": self.config.refit_every_episodes,
                "max_episodes": self.config.max_episodes}

    def state_dict(self) -> dict[str, Any]:
        n = self.count
        return {**self.base_state(), "sums": self.sums[:n].copy(), "returns": self.returns[:n].copy(),
                "lengths": self.lengths[:n].copy(), "head": self.head, "since_fit": self.since_fit,
                "fits": self.fits, "theta": self.theta.cpu(), "loss": self._loss}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_base_state(state)
        self.sums = np.asarray(state["sums"], dtype=np.float64).copy()
        self.returns = np.asarray(state["returns"], dtype=np.float64).copy()
        self.lengths = np.asarray(state["lengths"], dtype=np.float64).copy()
        self.count = int(self.sums.shape[0])
        self.head, self.since_fit, self.fits = int(state["head"]), int(state["since_fit"]), int(state["fits"])
        self.theta = state["theta"].to(self.ctx.device, torch.float32)
        self._loss = state["loss"]
