"""VIB — a variational-information-bottleneck reward model (Alemi, Fischer, Dillon and Murphy 2017,
"Deep Variational Information Bottleneck") fitted to episodic returns.

Definition (Alemi et al., eq. 7): a stochastic encoder p(z|x) = N(μ(x), diag σ²(x)) and a decoder
q(y|z) are trained to minimise ``E_x E_{z~p(z|x)} [−log q(y|z)] + β KL(p(z|x) ‖ r(z))`` with
r(z) = N(0, I) and the reparameterisation z = μ + σ ε; at test time the decoder is read at the mean
(or averaged over samples). The bottleneck keeps only what in x predicts y ("minimal sufficient").

Ours (x = (s, a), y = reward):

* **The target is only observed per trajectory.** There is no per-step label y, so the likelihood
  term is replaced by the return-decomposition loss of :mod:`mira.baselines.common`: per-step
  predictions decoded from *sampled* z, over a random K-step subsequence of an episode (RRD) or the
  whole episode (``loss="full"``), must add up to the episode's return. A Gaussian likelihood with
  fixed variance on the return gives the same squared error. The KL is applied per step (averaged
  over the sampled steps) with weight β.
* **The reward the agent learns on is the decoder at the encoder's mean**, r(s, a) = c · g(μ(s, a)),
  deterministic and without sampling noise; c is the reward scale of the common module.
* Inputs are [s, a], z-scored by running statistics of stored episodes; log σ is clamped to
  [−10, 2] for numerical safety. The encoder is an MLP (``hidden``), the decoder a smaller one
  (``decoder_hidden``).
* Logged: ``vib_loss`` (regression + β·KL), ``vib_kl`` (mean KL per step, nats, always ≥ 0).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import nn

from mira.baselines.common import ReturnDecompositionSource, mlp
from mira.baselines.config import VIBConfig

LOG_STD_MIN, LOG_STD_MAX = -10.0, 2.0


class VIBModel(nn.Module):
    """Gaussian encoder (s, a) → z and decoder z → per-step reward (in units of the reward scale)."""

    def __init__(self, in_dim: int, latent_dim: int, hidden: tuple[int, ...], decoder_hidden: tuple[int, ...]):
        super().__init__()
        self.latent_dim = latent_dim
        self.encoder = mlp(in_dim, hidden, 2 * latent_dim)
        self.decoder = mlp(latent_dim, decoder_hidden, 1)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, log_std = self.encoder(x).chunk(2, dim=-1)
        return mu, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(z).squeeze(-1)

    @staticmethod
    def kl_to_standard_normal(mu: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
        """KL(N(μ, σ²) ‖ N(0, I)) per row, summed over latent dimensions: ``[N]``, ≥ 0."""
        return 0.5 * (mu.pow(2) + (2.0 * log_std).exp() - 1.0 - 2.0 * log_std).sum(-1)


class VIBReward(ReturnDecompositionSource):
    """Bottlenecked reward model; the agent's reward is the decoder at the encoder's mean."""

    name = "vib"
    loss_field = "vib_loss"
    log_fields: ClassVar[tuple[str, ...]] = ("vib_loss", "vib_kl", "corr_dense")

    def __init__(self, config: VIBConfig | None = None) -> None:
        cfg = config or VIBConfig()
        if cfg.latent_dim <= 0 or cfg.beta < 0:
            raise ValueError("vib: latent_dim must be positive and beta >= 0")
        super().__init__(cfg)
        self.vib_config = cfg
        self._kl = torch.tensor(float("nan"))

    def input_dim(self) -> int:
        return self.ctx.obs_dim + self.ctx.act_dim

    def raw_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.cat((obs, action), dim=-1).to(self.device, torch.float32)

    def build_model(self, in_dim: int) -> nn.Module:
        cfg = self.vib_config
        return VIBModel(in_dim, cfg.latent_dim, tuple(cfg.hidden), tuple(cfg.decoder_hidden))

    def predict(self, x: torch.Tensor, *, train: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        model: VIBModel = self.model  # type: ignore[assignment]
        mu, log_std = model.encode(x)
        if not train:
            return model.decode(mu), None
        z = mu + log_std.exp() * torch.randn_like(mu)
        kl = model.kl_to_standard_normal(mu, log_std).mean()
        self._kl = kl.detach()
        return model.decode(z), self.vib_config.beta * kl

    def extra_metrics(self) -> dict[str, torch.Tensor]:
        return {"vib_kl": self._kl}

    def describe(self) -> dict[str, Any]:
        cfg = self.vib_config
        return {**super().describe(), "latent_dim": cfg.latent_dim, "beta": cfg.beta,
                "decoder_hidden": list(cfg.decoder_hidden), "reward": "decoder at the encoder's mean"}

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "kl": self._kl}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self._kl = state["kl"]
