"""Every PyTorch API MIRA uses that is not public, in one place.

The fused agent updates (:mod:`mira.agents.networks`, :mod:`mira.agents.gemm`) rely on a handful of
PyTorch internals that are stable in practice but carry no compatibility promise. They are named
here and nowhere else, and ``tests/test_torch_private.py`` checks each against a public reference, so
a PyTorch release that changes one fails loudly in the test suite instead of silently in a run. A run
does not rely on the test suite having been run against the user's PyTorch: :func:`fused_path_problem`
checks at start-up that each internal exists and computes what its public reference computes, and
where one does not, the agents take the plain autograd path (``AgentConfig.kernels = "plain"``), which
uses none of them, and say so. So MIRA asks only for a minimum PyTorch, not a range.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch

FUSED_ADAM = getattr(torch, "_fused_adam_", None)
"""``torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, *, amsgrad, lr,
beta1, beta2, weight_decay, eps, maximize, grad_scale, found_inf)``: the kernel behind
``Adam(fused=True).step()``, or None where this build has none."""


def foreach_lerp_(targets: Sequence[torch.Tensor], sources: Sequence[torch.Tensor], weight: float) -> None:
    """``t.lerp_(s, weight)`` for every pair, in one call (Polyak averaging of target networks); one call
    per pair where this build has no ``_foreach_lerp_`` (the plain path must not depend on it)."""
    fused = getattr(torch, "_foreach_lerp_", None)
    if fused is not None:
        fused(list(targets), list(sources), weight)
        return
    for t, s in zip(targets, sources, strict=True):
        t.lerp_(s, weight)


def foreach_add_(tensors: Sequence[torch.Tensor], value: float) -> None:
    """``t.add_(value)`` for every tensor, in one call (Adam's step counters)."""
    torch._foreach_add_(list(tensors), value)


def relu_backward(grad: torch.Tensor, output: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """``grad`` where ``output > 0``, else 0: ReLU's backward given its output (into ``out`` if given)."""
    if out is None:
        return torch.ops.aten.threshold_backward(grad, output, 0)
    return torch.ops.aten.threshold_backward.grad_input(grad, output, 0, grad_input=out)


def onednn_linear_available() -> bool:
    """Whether this build has oneDNN's fused linear (+ReLU) primitive."""
    return bool(torch.backends.mkldnn.is_available()) and hasattr(torch.ops.mkldnn, "_linear_pointwise")


def onednn_linear(a: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool) -> torch.Tensor:
    """``relu?(a @ weightᵀ + bias)`` through oneDNN's primitive (``weight [out, in]``, may be a view)."""
    return torch.ops.mkldnn._linear_pointwise(a, weight, bias, "relu" if relu else "none", [], "")


def optimizer_has_hooks(opt: torch.optim.Optimizer) -> bool:
    """Whether any step hook (this optimiser's or a global one) would run around ``opt.step()``."""
    from torch.optim import optimizer as optimizer_module

    return bool(opt._optimizer_step_pre_hooks or opt._optimizer_step_post_hooks
                or optimizer_module._global_optimizer_pre_hooks or optimizer_module._global_optimizer_post_hooks)


@functools.cache
def fused_path_problem() -> str | None:
    """Why the fused agent path cannot run on this PyTorch (None when it can): each internal it calls is
    run once on a tiny input and compared with its public reference. Cached for the process."""
    try:
        if FUSED_ADAM is None:
            return "torch._fused_adam_ is missing"
        gen = torch.Generator().manual_seed(0)
        p_ref = torch.randn(5, 3, generator=gen).requires_grad_(True)
        p_ours = p_ref.detach().clone()
        opt = torch.optim.Adam([p_ref], lr=1e-2, fused=True)
        m1, m2, step = torch.zeros_like(p_ours), torch.zeros_like(p_ours), torch.zeros(())
        for _ in range(2):
            grad = torch.randn(5, 3, generator=gen)
            p_ref.grad = grad.clone()
            opt.step()
            foreach_add_([step], 1.0)
            FUSED_ADAM([p_ours], [grad], [m1], [m2], [], [step], amsgrad=False, lr=1e-2, beta1=0.9, beta2=0.999,
                       weight_decay=0.0, eps=1e-8, maximize=False, grad_scale=None, found_inf=None)
        if not torch.allclose(p_ours, p_ref.detach()):
            return "torch._fused_adam_ no longer computes Adam's step"
        out = torch.tensor([-1.0, 0.0, 2.0])
        grad = torch.tensor([3.0, 4.0, 5.0])
        expected = torch.tensor([0.0, 0.0, 5.0])
        if not torch.equal(relu_backward(grad, out), expected):
            return "aten.threshold_backward no longer computes ReLU's backward"
        buffer = torch.empty(3)
        relu_backward(grad, out, out=buffer)
        if not torch.equal(buffer, expected):
            return "aten.threshold_backward.grad_input no longer writes ReLU's backward"
        probe = torch.zeros(2, 2)  # never the global generator: the self-test must not move a run's RNG
        if optimizer_has_hooks(torch.optim.SGD([probe.requires_grad_(True)], lr=0.1)):
            return "optimizer step hooks are reported where none were registered"
    except Exception as exc:  # any error means: do not use this path
        return f"{type(exc).__name__}: {exc}"
    return None
