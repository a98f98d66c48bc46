"""What the four trajectory-feedback baselines share.

* :class:`TrajectoryRewardSource`: a :class:`~mira.rewards.base.RewardSource` that samples only
  transitions of finished episodes, remembers finished episodes as row ranges of the replay buffer
  (:class:`~mira.rewards.episodes.EpisodeStore`), and logs ``corr_dense`` through the diagnostics
  module (never through its reward).
* :class:`RunningNorm`: running mean/variance of decoder inputs, updated once per finished episode
  (not per sampled batch, so the reward function only moves at episode boundaries).
* :class:`ReturnDecompositionSource`: a neural per-step reward model fitted so that its predictions
  over an episode sum to the episode's return — RRD's randomized-subsequence estimator (default) or
  RD's full-episode loss. LaRe and VIB differ only in the model's input and architecture.

Loss scaling (shared by LaRe and VIB, and a difference from RRD's written loss). RRD minimises
``(R - T/K Σ_{t∈I} r̂_t)²``. We minimise ``((R/T - mean_{t∈I} r̂_t) / c)²``, which is the same
estimator divided by ``(T c)²``: for fixed-length episodes a constant factor, for variable lengths a
per-episode weight 1/T² that keeps long episodes from dominating. ``c`` is the root mean square of
the per-step average return R/T over the episodes in the buffer; the network predicts ``u`` and the
reward is ``r̂ = c·u``. Without it, returns of 10⁴–10⁵ (HumanoidStandup) would make Adam's first steps
meaningless, and the agent still sees the reward in the environment's own units.

As in RRD, the randomized loss equals the full-episode loss plus the variance of the subsample mean,
so it also shrinks the within-episode spread of r̂ (RRD's regularisation); RRD's bias-corrected
variant is not implemented — ``loss="full"`` is the unregularised alternative.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from mira.baselines.config import DecoderConfig
from mira.baselines.diagnostics import dense_reward_correlation_for_logging
from mira.replay import Batch
from mira.rewards.base import RewardContext, RewardSource
from mira.rewards.episodes import EpisodeStore

#: Normalised decoder inputs are clipped to this many standard deviations.
INPUT_CLIP = 10.0
#: Floor of the reward scale c (RMS of R/T) so an all-zero history does not divide by zero.
MIN_SCALE = 1e-6


def mlp(in_dim: int, hidden: tuple[int, ...], out_dim: int) -> nn.Sequential:
    """A ReLU MLP ``in_dim -> hidden... -> out_dim``."""
    layers: list[nn.Module] = []
    prev = in_dim
    for width in hidden:
        layers += [nn.Linear(prev, int(width)), nn.ReLU()]
        prev = int(width)
    layers.append(nn.Linear(prev, out_dim))
    return nn.Sequential(*layers)


class TrajectoryRewardSource(RewardSource):
    """Base of IRCR, RD, LaRe and VIB: complete-episode sampling, an episode store, diagnostics."""

    needs_complete_episodes: ClassVar[bool] = True
    log_fields: ClassVar[tuple[str, ...]] = ("corr_dense",)

    def __init__(self, *, max_episodes: int = 100_000) -> None:
        self.max_episodes = max_episodes
        self._last: tuple[np.ndarray, torch.Tensor] | None = None

    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        self.store = EpisodeStore(ctx.buffer, self.max_episodes)
        self.rng = np.random.default_rng([int(ctx.seed), 0x5EED_BA5E])

    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> None:
        if self.store.add(rows, episode_return):
            self.episode_added(len(self.store) - 1, rows, float(episode_return))

    def episode_added(self, index: int, rows: np.ndarray, episode_return: float) -> None:
        """Hook for subclasses: a whole episode was stored at ``index`` of :attr:`store`."""

    # ------------------------------------------------------------------------------ relabelling
    def relabel(self, batch: Batch) -> torch.Tensor:
        reward = self.compute_reward(batch)
        self._last = (batch.indices, reward)
        return reward

    def compute_reward(self, batch: Batch) -> torch.Tensor:
        """The per-transition reward ``[B]`` (float32, on the batch's device); never requires grad."""
        raise NotImplementedError

    def diagnostics(self, batch: Batch) -> dict[str, torch.Tensor]:
        """``corr_dense`` of the reward given for ``batch`` (logging only; see :mod:`.diagnostics`)."""
        if self._last is not None and self._last[0] is batch.indices:
            reward = self._last[1]
        else:
            reward = self.compute_reward(batch)
        return {"corr_dense": dense_reward_correlation_for_logging(reward, self.ctx.buffer, batch.indices)}

    # ------------------------------------------------------------------------------- checkpoint
    def base_state(self) -> dict[str, Any]:
        return {"store": self.store.state_dict(), "rng": self.rng.bit_generator.state}

    def load_base_state(self, state: dict[str, Any]) -> None:
        self.store.load_state_dict(state["store"])
        self.rng.bit_generator.state = state["rng"]
        self._last = None


class RunningNorm:
    """Running mean and variance (Chan et al.'s parallel update, float64), applied as clipped z-scores."""

    def __init__(self, dim: int, device: torch.device) -> None:
        self.count = 0.0
        self.mean = np.zeros(dim, dtype=np.float64)
        self.m2 = np.zeros(dim, dtype=np.float64)
        self.device = device
        self._sync()

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.mean.shape[0])
        n = float(x.shape[0])
        if n == 0:
            return
        mean_b = x.mean(axis=0)
        m2_b = ((x - mean_b) ** 2).sum(axis=0)
        total = self.count + n
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2_b + delta**2 * (self.count * n / total)
        self.count = total
        self._sync()

    def _sync(self) -> None:
        var = self.m2 / max(self.count, 1.0)
        std = np.sqrt(np.maximum(var, 0.0)) + 1e-6
        if self.count == 0:
            std = np.ones_like(std)
        self._mean_t = torch.as_tensor(self.mean, dtype=torch.float32, device=self.device)
        self._inv_std_t = torch.as_tensor(1.0 / std, dtype=torch.float32, device=self.device)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self._mean_t) * self._inv_std_t).clamp(-INPUT_CLIP, INPUT_CLIP)

    def state_dict(self) -> dict[str, Any]:
        return {"count": self.count, "mean": self.mean.copy(), "m2": self.m2.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.count = float(state["count"])
        self.mean = np.asarray(state["mean"], dtype=np.float64).copy()
        self.m2 = np.asarray(state["m2"], dtype=np.float64).copy()
        self._sync()


class ReturnDecompositionSource(TrajectoryRewardSource):
    """A neural per-step reward model fitted so its per-step predictions sum to episodic returns.

    Subclasses give the model's raw input (:meth:`raw_inputs`), build it (:meth:`build_model`) and
    say how it maps normalised inputs to per-step predictions (:meth:`predict`).
    """

    loss_field: ClassVar[str] = "decoder_loss"

    def __init__(self, config: DecoderConfig) -> None:
        super().__init__(max_episodes=config.max_episodes)
        if config.loss not in ("rrd", "full"):
            raise ValueError(f"decoder loss must be 'rrd' or 'full', not {config.loss!r}")
        for name in ("fit_every", "fit_iters", "episodes_per_batch", "subseq_len", "min_episodes"):
            if int(getattr(config, name)) <= 0:
                raise ValueError(f"{name} must be positive, not {getattr(config, name)!r}")
        self.config = config
        self.scale = 1.0
        self.fits = 0

    # -- what subclasses provide
    def input_dim(self) -> int:
        raise NotImplementedError

    def raw_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Model inputs ``[N, D]`` (float32, on the source's device) of transitions ``(obs, action)``."""
        raise NotImplementedError

    def build_model(self, in_dim: int) -> nn.Module:
        raise NotImplementedError

    def predict(self, x: torch.Tensor, *, train: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Per-step prediction ``u`` ``[N]`` in units of :attr:`scale` from normalised inputs, and an
        extra loss term (a regulariser, e.g. VIB's KL) or None. ``train=False`` is the reward read-out."""
        raise NotImplementedError

    def extra_metrics(self) -> dict[str, torch.Tensor]:
        return {}

    # -- RewardSource
    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        self.device = ctx.device
        self.norm = RunningNorm(self.input_dim(), ctx.device)
        self.model = self.build_model(self.input_dim()).to(ctx.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.config.lr, foreach=True)
        self._loss = torch.tensor(float("nan"), device=ctx.device)

    def episode_added(self, index: int, rows: np.ndarray, episode_return: float) -> None:
        buf = self.ctx.buffer
        idx = torch.from_numpy(np.asarray(rows, dtype=np.int64))
        with torch.no_grad():
            x = self.raw_inputs(buf.obs[idx].to(self.device), buf.action[idx].to(self.device))
        self.norm.update(x.cpu().numpy())
        self._update_scale()

    def _update_scale(self) -> None:
        per_step = self.store.returns / np.maximum(self.store.length, 1)
        if per_step.size:
            self.scale = max(float(np.sqrt(np.mean(per_step**2))), MIN_SCALE)

    def reward_of(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The decoded per-step reward ``[N]`` of transitions, in the environment's units (no grad)."""
        with torch.no_grad():
            u, _ = self.predict(self.norm(self.raw_inputs(obs, action)), train=False)
            return u * self.scale

    def compute_reward(self, batch: Batch) -> torch.Tensor:
        return self.reward_of(batch.obs, batch.action).to(batch.reward.device)

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        cfg = self.config
        if step % cfg.fit_every == 0 and self.store.n_intact() >= cfg.min_episodes:
            for _ in range(cfg.fit_iters):
                self._loss = self.fit_step()
        out = {self.loss_field: self._loss} if self.fits else {}  # no fit yet: nothing to report (not NaN)
        out.update(self.extra_metrics())
        out.update(self.diagnostics(batch))
        return out

    def fit_step(self) -> torch.Tensor:
        """One gradient step of the return-decomposition loss on a batch of stored episodes."""
        cfg = self.config
        idx = self.store.sample(cfg.episodes_per_batch, self.rng)
        rows, mask = self.store.step_rows(idx, self.rng, cfg.subseq_len if cfg.loss == "rrd" else None)
        loss = self.decomposition_loss(rows, mask, self.store.returns[idx], self.store.length[idx])
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.fits += 1
        return loss.detach()

    def decomposition_loss(
        self, rows: np.ndarray, mask: np.ndarray, returns: np.ndarray, lengths: np.ndarray
    ) -> torch.Tensor:
        """``mean_e ((R_e/T_e)/c - mean_{t∈I_e} u_t)²`` (+ the model's regulariser) for rows ``[E, L]``."""
        buf = self.ctx.buffer
        flat = torch.from_numpy(rows.reshape(-1))
        x = self.raw_inputs(buf.obs[flat].to(self.device), buf.action[flat].to(self.device))
        u, extra = self.predict(self.norm(x), train=True)
        m = torch.from_numpy(mask).to(self.device, torch.float32)
        u = u.reshape(m.shape) * m
        pred = u.sum(1) / m.sum(1).clamp_min(1.0)
        target = torch.as_tensor(returns / np.maximum(lengths, 1) / self.scale, dtype=torch.float32,
                                 device=self.device)
        loss = (pred - target).pow(2).mean()
        if extra is not None:
            loss = loss + extra
        return loss

    def describe(self) -> dict[str, Any]:
        cfg = self.config
        return {"method": self.name, "loss": cfg.loss, "subseq_len": cfg.subseq_len,
                "episodes_per_batch": cfg.episodes_per_batch, "hidden": list(cfg.hidden), "lr": cfg.lr,
                "fit_every": cfg.fit_every, "fit_iters": cfg.fit_iters}

    def state_dict(self) -> dict[str, Any]:
        return {**self.base_state(), "model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "norm": self.norm.state_dict(), "scale": self.scale, "fits": self.fits, "loss": self._loss.cpu()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_base_state(state)
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.norm.load_state_dict(state["norm"])
        self.scale = float(state["scale"])
        self.fits = int(state["fits"])
        self._loss = state["loss"].to(self.device)
