"""Networks shared by SAC and DDPG, and the autograd-free kernels their updates run on.

The twin critics of SAC are one *ensemble* module: every layer holds the weights of all critics as a
``[E, in, out]`` tensor and runs as a single batched matmul (``baddbmm``), so two critics cost one
kernel call per layer instead of two, forward and backward. DDPG uses the same module with E = 1.

The modules (``forward``, ``sample``, ...) are what acting, evaluation and the monitor use. The
agents' updates instead run :class:`EnsembleQKernels` and :class:`MLPKernels`, which compute the same
forward passes and explicit backward passes on activation / gradient buffers reused across updates,
with :func:`squashed_gaussian_forward` / :func:`squashed_gaussian_backward` for SAC's policy and
:class:`AdamStepper` for the optimisers. Why they are faster: no per-op autograd graph or fresh
allocations, ReLUs in place, a GEMV for the critics' width-1 output layer, the actor's loss
backpropagated through ``min_e Q_e`` only where each critic is the minimum, and no
``Optimizer.step`` bookkeeping. The plain updates (``AgentConfig.kernels = "plain"``) are the
reference they are tested against.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from mira.agents import gemm
from mira.agents.torch_private import FUSED_ADAM, foreach_add_, optimizer_has_hooks, relu_backward


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
        self.layers = nn.ModuleList(EnsembleLinear(ensemble, i, o) for i, o in itertools.pairwise(sizes))

    def params(self) -> list[torch.Tensor]:
        """``[W_1, b_1, ..., W_L, b_L]``, the order :func:`ensemble_q` and ``forward(params=)`` take."""
        out: list[torch.Tensor] = []
        for layer in self.layers:
            assert isinstance(layer, EnsembleLinear)
            out += (layer.weight, layer.bias)
        return out

    def forward(self, obs: torch.Tensor, action: torch.Tensor,
                params: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        """``Q_e(obs, action)`` for every member, ``[E, B]``; ``params`` replaces the module's own
        parameters (e.g. detached ones, so that no gradient reaches the critic)."""
        x = torch.cat((obs, action), dim=-1)
        return ensemble_q(self.params() if params is None else params, x, self.ensemble)


class EnsembleQKernels:
    """Autograd-free training passes of an :class:`EnsembleQ`, on activation and gradient buffers
    that are allocated once per batch size and reused.

    The critics are the large part of an update (``[E, B, H]`` activations), and running them through
    autograd costs a graph node, a fresh allocation (on CPU, page faults) and a Python dispatch for
    every step of every layer. These kernels do the same arithmetic with explicit backward formulas:

    * :meth:`forward` runs all members on ``x [B, in]`` and keeps the post-ReLU activations;
    * :meth:`backward` takes ``dL/dq [E, B]`` and writes the parameter gradients into ``grads``
      (the values autograd would produce, up to float rounding);
    * :meth:`input_grad_of_min` gives ``dL/dx`` for a loss on ``min_e Q_e`` (the actor's).

    Every call must run under ``torch.no_grad()``; results live in the buffers until the next call.
    """

    def __init__(self, critic: EnsembleQ) -> None:
        self.ensemble = critic.ensemble
        self.widths: list[int] = [int(layer.weight.shape[2]) for layer in critic.layers
                                  if isinstance(layer, EnsembleLinear)]
        self._bufs: dict[tuple[int, torch.dtype, torch.device], tuple[list[torch.Tensor], list[torch.Tensor],
                                                                      torch.Tensor]] = {}
        self._x: torch.Tensor | None = None
        self._cur: tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor] | None = None

    def _buffers(self, x: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor]:
        key = (x.shape[0], x.dtype, x.device)
        bufs = self._bufs.get(key)
        if bufs is None:
            e, b = self.ensemble, x.shape[0]
            hidden = self.widths[:-1]
            bufs = ([x.new_empty(e, b, w) for w in hidden], [x.new_empty(e, b, w) for w in hidden],
                    x.new_empty(e, b))
            if len(self._bufs) >= 4:  # a few batch sizes at a time
                self._bufs.clear()
            self._bufs[key] = bufs
        return bufs

    def _inputs(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The input of every layer of the last forward (``x`` broadcast over members, then the
        hidden activations) and the gradient buffers."""
        x, bufs = self._x, self._cur
        if x is None or bufs is None:
            raise RuntimeError("backward before forward")
        return [x.expand(self.ensemble, -1, -1), *bufs[0]], bufs[1]

    def forward(self, params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """``Q_e(x)`` for every member, ``[E, B]`` (a buffer, overwritten by the next forward)."""
        bufs = self._cur = self._buffers(x)
        acts, _, q = bufs
        e = self.ensemble
        h = x.expand(e, -1, -1)
        last = len(params) - 2
        for i in range(0, last, 2):
            h = gemm.bmm(h, params[i], params[i + 1], relu=True, out=acts[i // 2])
        w, b = params[last], params[last + 1]
        for m in range(e):  # width-1 output: one GEMV per member (MKL's batched GEMM is slow at N = 1)
            torch.mv(h[m], w[m, :, 0], out=q[m])
        q += b.view(e, 1)
        self._x = x
        return q

    def backward(self, params: Sequence[torch.Tensor], dq: torch.Tensor, grads: Sequence[torch.Tensor]) -> None:
        """Write ``dL/dparams`` into ``grads`` (same shapes as ``params``) given ``dq = dL/dq [E, B]``
        of the last :meth:`forward` (``x`` gets no gradient)."""
        ins, gbufs = self._inputs()
        e = self.ensemble
        last = len(params) - 2
        h = ins[-1]
        for m in range(e):  # output layer: dW = h^T dq (GEMV), db = sum dq
            torch.mv(h[m].t(), dq[m], out=grads[last][m, :, 0])
        torch.sum(dq, 1, out=grads[last + 1].view(e))
        if last == 0:
            return
        # dL/d(pre-activation of the last hidden layer): dq (x) w, where the ReLU was active.
        g = torch.mul(dq.unsqueeze(-1), params[last].transpose(1, 2), out=gbufs[-1])
        relu_backward(g, h, out=g)
        for i in range(last - 2, -1, -2):
            inp = ins[i // 2]
            gemm.bmm(inp.transpose(1, 2), g, out=grads[i])
            torch.sum(g, 1, keepdim=True, out=grads[i + 1])
            if i > 0:
                g_in = gemm.bmm(g, params[i].transpose(1, 2), out=gbufs[i // 2 - 1])
                g = relu_backward(g_in, inp, out=g_in)

    def input_grad_of_min(self, params: Sequence[torch.Tensor], argmin: torch.Tensor | None, scale: float,
                          input_cols: slice) -> torch.Tensor:
        """``dL/dx[:, input_cols]`` for ``L = scale * sum_b q[argmin_b, b]`` after :meth:`forward`
        (``argmin [B]``: the member each row's minimum came from; ``None`` when there is one member).

        That is the actor's loss through ``min_e Q_e`` (autograd's ``min`` sends each row's gradient
        to its argmin member); each member only backpropagates the rows where it was the minimum,
        which halves the matmul work for twin critics. The critics' parameters get no gradient.
        """
        ins, _ = self._inputs()
        last = len(params) - 2
        w0 = params[0][:, input_cols, :]
        if argmin is None and self.ensemble != 1:
            raise ValueError("argmin is required with more than one member")
        dx = None if argmin is None else ins[0].new_zeros(ins[0].shape[1], w0.shape[1])
        for m in range(self.ensemble):
            idx = None if argmin is None else (argmin == m).nonzero().squeeze(1)
            if idx is not None and idx.numel() == 0:
                continue

            def rows(t: torch.Tensor, idx: torch.Tensor | None = idx) -> torch.Tensor:
                return t if idx is None else t.index_select(0, idx)

            w_out = params[last][m, :, 0] * scale
            if last == 0:  # no hidden layer: dL/dx = scale * w
                g = w_out[input_cols].expand(ins[0].shape[1] if idx is None else idx.numel(), -1)
            else:
                h = rows(ins[-1][m])
                g = relu_backward(w_out.expand_as(h), h)
                for i in range(last - 2, 0, -2):
                    inp = rows(ins[i // 2][m])
                    g = gemm.matmul(g, params[i][m].t())
                    g = relu_backward(g, inp, out=g)
                g = gemm.matmul(g, w0[m].t())
            if dx is None:
                return g.contiguous()
            dx.index_copy_(0, idx, g)  # type: ignore[arg-type]
        assert dx is not None
        return dx


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


def relu_mlp_1d(params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """:func:`relu_mlp` on one input vector ``x [in]`` (matrix-vector products: acting, one step at
    a time, is latency-bound)."""
    last = len(params) - 2
    for i in range(0, last, 2):
        x = torch.addmv(params[i + 1], params[i], x).relu_()
    return torch.addmv(params[last + 1], params[last], x)


def _linear_params(modules: Sequence[nn.Module]) -> list[torch.Tensor]:
    out: list[torch.Tensor] = []
    for m in modules:
        if isinstance(m, nn.Linear):
            out += (m.weight, m.bias)
    return out


class MLPKernels:
    """Autograd-free training passes of a ReLU MLP given as ``nn.Linear`` parameters
    ``[W_1, b_1, ..., W_L, b_L]`` (``W_l: [out, in]``), on activation buffers reused across calls
    (the actor's counterpart of :class:`EnsembleQKernels`; same rules: run under ``torch.no_grad()``,
    results live until the next :meth:`forward`)."""

    def __init__(self, params: Sequence[torch.Tensor]) -> None:
        self.widths = [params[i].shape[0] for i in range(0, len(params), 2)]
        self._bufs: dict[tuple[int, torch.dtype, torch.device], tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
        self._x: torch.Tensor | None = None
        self._cur: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None

    def _buffers(self, x: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        key = (x.shape[0], x.dtype, x.device)
        bufs = self._bufs.get(key)
        if bufs is None:
            b = x.shape[0]
            bufs = ([x.new_empty(b, w) for w in self.widths], [x.new_empty(b, w) for w in self.widths])
            if len(self._bufs) >= 4:  # a few batch sizes at a time
                self._bufs.clear()
            self._bufs[key] = bufs
        return bufs

    def forward(self, params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """The MLP's (pre-activation) output ``[B, out]``, a buffer."""
        bufs = self._cur = self._buffers(x)
        acts = bufs[0]
        self._x = x
        h = x
        last = len(params) - 2
        for i in range(0, last, 2):
            h = gemm.matmul(h, params[i].t(), params[i + 1], relu=True, out=acts[i // 2])
        return gemm.matmul(h, params[last].t(), params[last + 1], out=acts[-1])

    def backward(self, params: Sequence[torch.Tensor], g_out: torch.Tensor, grads: Sequence[torch.Tensor],
                 rows: slice | None = None) -> None:
        """Write ``dL/dparams`` into ``grads`` given ``g_out = dL/doutput`` of the last forward (the
        input gets no gradient). With ``rows``, only those rows of the last forward's batch enter the
        loss (``g_out`` has just those rows)."""
        x, bufs = self._x, self._cur
        assert x is not None and bufs is not None, "backward() before forward()"
        acts, gbufs = bufs
        if rows is not None:
            x, acts = x[rows], [a[rows] for a in acts]
        n = x.shape[0]
        g = g_out
        for i in range(len(params) - 2, -1, -2):
            layer = i // 2
            inp = acts[layer - 1] if layer > 0 else x
            gemm.matmul(g.t(), inp, out=grads[i])
            torch.sum(g, 0, out=grads[i + 1])
            if layer > 0:
                g_in = gemm.matmul(g, params[i], out=gbufs[layer - 1][:n])
                g = relu_backward(g_in, inp, out=g_in)


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
        return self._squash(mean, log_std, torch.randn_like(mean))

    def sample_with(self, obs: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`sample` with the standard normal draw given (``noise [B, A]``)."""
        mean, log_std = self.distribution(obs)
        return self._squash(mean, log_std, noise)

    def _squash(self, mean: torch.Tensor, log_std: torch.Tensor, noise: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        std = log_std.exp()
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


def squashed_gaussian_forward(out: torch.Tensor, noise: torch.Tensor
                              ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...]]:
    """:meth:`SquashedGaussianActor.sample` from the network's output ``[B, 2A]`` and the standard
    normal ``noise [B, A]``: ``(action, log_prob, saved)``, ``saved`` being what
    :func:`squashed_gaussian_backward` needs. Autograd-free (run under ``torch.no_grad()``)."""
    mean, raw = out.chunk(2, dim=-1)
    t = torch.tanh(raw)
    log_std = t * _LOG_STD_HALF + _LOG_STD_MID
    std = log_std.exp()
    pre = torch.addcmul(mean, std, noise)
    action = torch.tanh(pre)
    u = F.softplus(-2.0 * pre).add_(pre).sub_(_LOG2)
    log_prob = u.mul_(2.0).sub_(noise.square().mul_(0.5)).sub_(log_std).sum(-1).sub_(mean.shape[-1] * _HALF_LOG_2PI)
    return action, log_prob, (t, std, noise, action)


def squashed_gaussian_backward(saved: tuple[torch.Tensor, ...], g_action: torch.Tensor,
                               g_log_prob: torch.Tensor) -> torch.Tensor:
    """``dL/d out [B, 2A]`` of :func:`squashed_gaussian_forward` given ``dL/daction [B, A]`` and
    ``dL/dlog_prob`` (``[B]`` or a scalar broadcast over rows). With ``u = softplus(-2 pre) + pre -
    log 2``, ``du/dpre = tanh(pre)``, so ``dL/dpre = g_a (1 - a^2) + 2 g_lp a``; then ``dL/dmean =
    dL/dpre`` and ``dL/draw = (dL/dpre * std * noise - g_lp) * (MAX - MIN) / 2 * (1 - tanh(raw)^2)``."""
    t, std, noise, action = saved
    g_lp = g_log_prob.unsqueeze(-1) if g_log_prob.dim() == 1 else g_log_prob
    g_pre = torch.addcmul(g_action, g_action, action.square(), value=-1.0).add_(action * (2.0 * g_lp))
    one_minus_t2 = torch.addcmul(t.new_ones(()), t, t, value=-1.0)  # d tanh(raw) / d raw
    g_raw = (g_pre * std).mul_(noise).sub_(g_lp).mul_(one_minus_t2).mul_(_LOG_STD_HALF)
    return torch.cat((g_pre, g_raw), dim=-1)


class DeterministicActor(nn.Module):
    """DDPG's policy: ``tanh(MLP(s))``."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.net = mlp(obs_dim, hidden, act_dim)

    def params(self) -> list[torch.Tensor]:
        return _linear_params(list(self.net))

    def forward(self, obs: torch.Tensor, params: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        return torch.tanh(relu_mlp(self.params() if params is None else params, obs))


def make_adam(params: list[nn.Parameter] | list[torch.Tensor], lr: float) -> torch.optim.Adam:
    """Adam with the fastest implementation the device supports (fused kernels where available)."""
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr, foreach=True)




class AdamStepper:
    """``opt.step()`` for several ``torch.optim.Adam`` optimisers at once, as one fused-kernel call
    per distinct set of hyperparameters.

    The optimisers stay the source of truth (their state dicts, param groups and learning rates are
    read on every step), and the arithmetic is exactly that of ``Adam(fused=True).step()``: the step
    counters are incremented, then the fused Adam kernel
    (:data:`~mira.agents.torch_private.FUSED_ADAM`) updates parameters and moments in place.
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
            foreach_add_(steps, 1)
            FUSED_ADAM(params, grads, m1, m2, [], steps, amsgrad=False, lr=lr, beta1=beta1, beta2=beta2,  # type: ignore[misc]
                        weight_decay=wd, eps=eps, maximize=False, grad_scale=None, found_inf=None)

    @staticmethod
    def _fast_ok(opt: torch.optim.Optimizer) -> bool:
        if FUSED_ADAM is None or type(opt) is not torch.optim.Adam or optimizer_has_hooks(opt):
            return False
        for g in opt.param_groups:
            if (not g.get("fused") or g.get("amsgrad") or g.get("maximize") or g.get("capturable")
                    or g.get("differentiable") or g.get("decoupled_weight_decay")
                    or isinstance(g["lr"], torch.Tensor) or any(isinstance(b, torch.Tensor) for b in g["betas"])):
                return False
        return True
