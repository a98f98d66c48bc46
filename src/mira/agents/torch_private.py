"""Every PyTorch API MIRA uses that is not public, in one place.

The fused agent updates (:mod:`mira.agents.networks`, :mod:`mira.agents.gemm`) rely on a handful of
PyTorch internals that are stable in practice but carry no compatibility promise. They are named
here and nowhere else, and ``tests/test_torch_private.py`` checks each against a public reference, so
a PyTorch release that changes one fails loudly in the test suite instead of silently in a run; the
``torch`` range in ``pyproject.toml`` is the one that test has been run on. The plain agent updates
(``AgentConfig.kernels = "plain"``) use none of them.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

FUSED_ADAM = getattr(torch, "_fused_adam_", None)
"""``torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, *, amsgrad, lr,
beta1, beta2, weight_decay, eps, maximize, grad_scale, found_inf)``: the kernel behind
``Adam(fused=True).step()``, or None where this build has none."""


def foreach_lerp_(targets: Sequence[torch.Tensor], sources: Sequence[torch.Tensor], weight: float) -> None:
    """``t.lerp_(s, weight)`` for every pair, in one call (Polyak averaging of target networks)."""
    torch._foreach_lerp_(list(targets), list(sources), weight)


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
