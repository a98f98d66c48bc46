"""Networks shared by SAC and DDPG, and the small pieces of their updates that are tuned for speed.

The twin critics of SAC are one *ensemble* module: every layer holds the weights of all critics as a
``[E, in, out]`` tensor and runs as a single batched matmul (``baddbmm``), so two critics cost one
kernel call per layer instead of two, forward and backward. DDPG uses the same module with E = 1.

Performance notes (measured on a 2-core AVX2 CPU, batch 256, 2x256 ReLU nets; see bench/RESULTS.md):

* every module can run on an explicit list of its parameters (``params=``). The actor's loss runs the
  critic on *detached* parameters, which is what ``critic.requires_grad_(False)`` did, without
  toggling flags on every update;
* ReLUs run in place on the fresh output of their matmul (one [E, B, H] allocation less per layer:
  on CPU, fresh large allocations cost page faults);
* the critic's output layer (width 1) is a ``vecdot`` instead of a ``baddbmm``: MKL's batched GEMM
  with N = 1 (forward) and K = 1 (its backward, an outer product) is several times slower than the
  equivalent broadcast multiply-and-reduce;
* :class:`AdamStepper` applies Adam with one call of the fused kernel per group of optimisers,
  skipping ``Optimizer.step``'s Python bookkeeping (same arithmetic as ``Adam(fused=True).step()``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

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


def ensemble_q(params: Sequence[torch.Tensor], x: torch.Tensor, ensemble: int) -> torch.Tensor:
    """``E`` ReLU Q-networks on ``x [B, in]`` given their parameters ``[W_1, b_1, ..., W_L, b_L]``
    (``W_l: [E, in, out]``, ``b_l: [E, 1, out]``, the last layer of width 1); returns ``[E, B]``."""
    h = x.expand(ensemble, -1, -1)
    last = len(params) - 2
    for i in range(0, last, 2):
        h = torch.baddbmm(params[i + 1], h, params[i]).relu_()
    # Width-1 output layer: h [E, B, H] . w [E, 1, H] -> [E, B] (see the module docstring).
    return torch.linalg.vecdot(h, params[last].transpose(1, 2)) + params[last + 1].squeeze(-1)


class EnsembleQ(nn.Module):
    """``E`` Q-networks ``Q_e(s, a)`` with ReLU hidden layers, returning ``[E, B]``."""

    def __init__(self, ensemble: int, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.ensemble = ensemble
        sizes = (obs_dim + act_dim, *hidden, 1)
        self.layers = nn.ModuleList(EnsembleLinear(ensemble, i, o) for i, o in zip(sizes[:-1], sizes[1:], strict=True))

    def params(self) -> list[torch.Tensor]:
        """``[W_1, b_1, ..., W_L, b_L]``, the order :func:`ensemble_q` and ``forward(params=)`` take."""
        out: list[torch.Tensor] = []
        for layer in self.layers:
            out += (layer.weight, layer.bias)
        return out

    def forward(self, obs: torch.Tensor, action: torch.Tensor,
                params: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        """``Q_e(obs, action)`` for every member, ``[E, B]``; ``params`` replaces the module's own
        parameters (e.g. detached ones, so that no gradient reaches the critic)."""
        x = torch.cat((obs, action), dim=-1)
        return ensemble_q(self.params() if params is None else params, x, self.ensemble)


def mlp(in_dim: int, hidden: tuple[int, ...], out_dim: int) -> nn.Sequential:
    """A ReLU MLP ``in_dim -> hidden... -> out_dim``."""
    layers: list[nn.Module] = []
    prev = in_dim
    for width in hidden:
        layers += [nn.Linear(prev, width), nn.ReLU()]
        prev = width
    layers.append(nn.Linear(prev, out_dim))
    return nn.Sequential(*layers)


def relu_mlp(params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """The ReLU MLP whose ``nn.Linear`` parameters are ``[W_1, b_1, ..., W_L, b_L]`` (no output
    activation). ReLUs run in place on each layer's fresh output."""
    last = len(params) - 2
    for i in range(0, last, 2):
        x = F.linear(x, params[i], params[i + 1]).relu_()
    return F.linear(x, params[last], params[last + 1])


def _linear_params(modules: Sequence[nn.Module]) -> list[torch.Tensor]:
    out: list[torch.Tensor] = []
    for m in modules:
        if isinstance(m, nn.Linear):
            out += (m.weight, m.bias)
    return out


LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
_LOG_STD_MID = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN)
_LOG_STD_HALF = 0.5 * (LOG_STD_MAX - LOG_STD_MIN)
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)
_LOG2 = math.log(2.0)


class SquashedGaussianActor(nn.Module):
    """SAC's policy: a Gaussian over pre-squash actions, squashed by tanh into [-1, 1]."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.trunk = mlp(obs_dim, hidden[:-1], hidden[-1]) if len(hidden) > 1 else nn.Linear(obs_dim, hidden[0])
        self.head = nn.Linear(hidden[-1], 2 * act_dim)
        self.act_dim = act_dim

    def params(self) -> list[torch.Tensor]:
        """The linear layers' parameters in order, trunk then head (see :func:`relu_mlp`)."""
        trunk = list(self.trunk) if isinstance(self.trunk, nn.Sequential) else [self.trunk]
        return _linear_params([*trunk, self.head])

    def distribution(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the pre-squash Gaussian."""
        mean, raw = relu_mlp(self.params(), obs).chunk(2, dim=-1)
        # Soft clamp keeps gradients alive near the bounds (as in CleanRL's SAC):
        # log_std = MIN + (MAX - MIN) / 2 * (tanh(raw) + 1).
        log_std = torch.tanh(raw).mul(_LOG_STD_HALF).add_(_LOG_STD_MID)  # tanh's backward needs its output
        return mean, log_std

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the pre-squash Gaussian (so ``functional_call`` works on snapshots)."""
        return self.distribution(obs)

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised squashed sample and its log-probability ``[B]``."""
        mean, log_std = self.distribution(obs)
        std = log_std.exp()
        noise = torch.randn_like(mean)
        pre = torch.addcmul(mean, std, noise)
        action = torch.tanh(pre)
        # log N(pre; mean, std) - sum log(1 - tanh(pre)^2), the latter in the numerically stable form
        # 2 (log 2 - pre - softplus(-2 pre)); with u = softplus(-2 pre) + pre - log 2 it is, in one sum,
        # sum(2 u - noise^2 / 2 - log_std) - |A| log(2 pi) / 2.
        u = F.softplus(-2.0 * pre).add_(pre).sub_(_LOG2)
        per_dim = u.mul_(2.0).sub_(noise.square().mul_(0.5)).sub_(log_std)
        log_prob = per_dim.sum(-1).sub_(self.act_dim * _HALF_LOG_2PI)
        return action, log_prob

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        mean, _ = self.distribution(obs)
        return torch.tanh(mean)


class DeterministicActor(nn.Module):
    """DDPG's policy: ``tanh(MLP(s))``."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.net = mlp(obs_dim, hidden, act_dim)

    def params(self) -> list[torch.Tensor]:
        return _linear_params(list(self.net))

    def forward(self, obs: torch.Tensor, params: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        return torch.tanh(relu_mlp(self.params() if params is None else params, obs))


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


_FUSED_ADAM = getattr(torch, "_fused_adam_", None)


class AdamStepper:
    """``opt.step()`` for several ``torch.optim.Adam`` optimisers at once, as one fused-kernel call
    per distinct set of hyperparameters.

    The optimisers stay the source of truth (their state dicts, param groups and learning rates are
    read on every step), and the arithmetic is exactly that of ``Adam(fused=True).step()``: the step
    counters are incremented, then ``torch._fused_adam_`` updates parameters and moments in place.
    Whatever the fast path does not cover (non-fused optimisers, AMSGrad, maximize, capturable or
    differentiable modes, tensor learning rates, optimizer hooks, parameters still without state, a
    PyTorch without the kernel) falls back to the optimiser's own ``step()``.
    """

    def __init__(self, *optimizers: torch.optim.Adam) -> None:
        self.optimizers = optimizers

    def zero_grad(self) -> None:
        for opt in self.optimizers:
            for group in opt.param_groups:
                for p in group["params"]:
                    p.grad = None

    def step(self) -> None:
        calls: dict[tuple[float, float, float, float, float], tuple[list[torch.Tensor], ...]] = {}
        for opt in self.optimizers:
            if not self._fast_ok(opt):
                opt.step()
                continue
            pending: list[tuple[tuple[float, float, float, float, float], torch.Tensor, dict]] = []
            fast = True
            for group in opt.param_groups:
                beta1, beta2 = group["betas"]
                key = (group["lr"], float(beta1), float(beta2), group["weight_decay"], group["eps"])
                for p in group["params"]:
                    if p.grad is None:
                        continue
                    st = opt.state.get(p)
                    if not st or p.device.type != "cpu" or p.grad.is_sparse:
                        fast = False
                        break
                    pending.append((key, p, st))
                if not fast:
                    break
            if not fast:
                opt.step()
                continue
            for key, p, st in pending:
                lists = calls.setdefault(key, ([], [], [], [], []))
                lists[0].append(p)
                lists[1].append(p.grad)  # type: ignore[arg-type]
                lists[2].append(st["exp_avg"])
                lists[3].append(st["exp_avg_sq"])
                lists[4].append(st["step"])
        for (lr, beta1, beta2, wd, eps), (params, grads, m1, m2, steps) in calls.items():
            torch._foreach_add_(steps, 1)
            _FUSED_ADAM(params, grads, m1, m2, [], steps, amsgrad=False, lr=lr, beta1=beta1, beta2=beta2,  # type: ignore[misc]
                        weight_decay=wd, eps=eps, maximize=False, grad_scale=None, found_inf=None)

    @staticmethod
    def _fast_ok(opt: torch.optim.Optimizer) -> bool:
        if _FUSED_ADAM is None or type(opt) is not torch.optim.Adam:
            return False
        if opt._optimizer_step_pre_hooks or opt._optimizer_step_post_hooks:  # type: ignore[attr-defined]
            return False
        from torch.optim import optimizer as _optimizer_mod

        if _optimizer_mod._global_optimizer_pre_hooks or _optimizer_mod._global_optimizer_post_hooks:
            return False
        for g in opt.param_groups:
            if (not g.get("fused") or g.get("amsgrad") or g.get("maximize") or g.get("capturable")
                    or g.get("differentiable") or g.get("decoupled_weight_decay")
                    or isinstance(g["lr"], torch.Tensor) or any(isinstance(b, torch.Tensor) for b in g["betas"])):
                return False
        return True
