"""Networks shared by SAC and DDPG.

The twin critics of SAC are one *ensemble* module: every layer holds the weights of all critics as a
``[E, in, out]`` tensor and runs as a single batched matmul (``baddbmm``), so two critics cost one
kernel call per layer instead of two, forward and backward. DDPG uses the same module with E = 1.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


class EnsembleLinear(nn.Module):
    """``E`` independent linear layers evaluated in one batched matmul: ``[E, B, in] -> [E, B, out]``."""

    def __init__(self, ensemble: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(ensemble, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(ensemble, 1, out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Same distribution as nn.Linear's default init, per ensemble member.
        fan_in = self.weight.shape[1]
        bound = 1.0 / math.sqrt(fan_in)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class EnsembleQ(nn.Module):
    """``E`` Q-networks ``Q_e(s, a)`` with ReLU hidden layers, returning ``[E, B]``."""

    def __init__(self, ensemble: int, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.ensemble = ensemble
        sizes = (obs_dim + act_dim, *hidden, 1)
        self.layers = nn.ModuleList(EnsembleLinear(ensemble, i, o) for i, o in zip(sizes[:-1], sizes[1:], strict=True))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat((obs, action), dim=-1).unsqueeze(0).expand(self.ensemble, -1, -1)
        for layer in self.layers[:-1]:
            x = F.relu(layer(x))
        return self.layers[-1](x).squeeze(-1)


def mlp(in_dim: int, hidden: tuple[int, ...], out_dim: int) -> nn.Sequential:
    """A ReLU MLP ``in_dim -> hidden... -> out_dim``."""
    layers: list[nn.Module] = []
    prev = in_dim
    for width in hidden:
        layers += [nn.Linear(prev, width), nn.ReLU()]
        prev = width
    layers.append(nn.Linear(prev, out_dim))
    return nn.Sequential(*layers)


LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


class SquashedGaussianActor(nn.Module):
    """SAC's policy: a Gaussian over pre-squash actions, squashed by tanh into [-1, 1]."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.trunk = mlp(obs_dim, hidden[:-1], hidden[-1]) if len(hidden) > 1 else nn.Linear(obs_dim, hidden[0])
        self.head = nn.Linear(hidden[-1], 2 * act_dim)
        self.act_dim = act_dim

    def distribution(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the pre-squash Gaussian."""
        mean, raw = self.head(F.relu(self.trunk(obs))).chunk(2, dim=-1)
        # Soft clamp keeps gradients alive near the bounds (as in CleanRL's SAC).
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(raw) + 1.0)
        return mean, log_std

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised squashed sample and its log-probability ``[B]``."""
        mean, log_std = self.distribution(obs)
        std = log_std.exp()
        noise = torch.randn_like(mean)
        pre = mean + std * noise
        action = torch.tanh(pre)
        # log N(pre; mean, std) - sum log(1 - tanh(pre)^2), the latter in a numerically stable form.
        log_prob = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))).sum(-1)
        return action, log_prob

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        mean, _ = self.distribution(obs)
        return torch.tanh(mean)


class DeterministicActor(nn.Module):
    """DDPG's policy: ``tanh(MLP(s))``."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.net = mlp(obs_dim, hidden, act_dim)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(obs))


def polyak_update(online: nn.Module, target: nn.Module, tau: float) -> None:
    """``target <- (1 - tau) target + tau online`` in one fused foreach call."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(online.parameters()), tau)


def make_adam(params: list[nn.Parameter] | list[torch.Tensor], lr: float) -> torch.optim.Adam:
    """Adam with the fastest implementation the device supports (fused kernels where available)."""
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr, foreach=True)
