"""The PyTorch internals of :mod:`mira.agents.torch_private`, each checked against a public reference.

A PyTorch release that renames, removes or changes one of them fails here, by name; a run on such a
release finds it at start-up (``fused_path_problem``) and takes the plain autograd update.
"""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from mira.agents import torch_private as tp


def test_fused_adam_kernel_is_adam() -> None:
    assert tp.FUSED_ADAM is not None, "torch._fused_adam_ is gone: the fused agent path falls back to opt.step()"
    torch.manual_seed(0)
    p_ref = torch.randn(7, 3, requires_grad=True)
    p_ours = p_ref.detach().clone()
    opt = torch.optim.Adam([p_ref], lr=1e-2, fused=True)
    m1, m2, step = torch.zeros_like(p_ours), torch.zeros_like(p_ours), torch.zeros(())
    for _ in range(3):
        grad = torch.randn(7, 3)
        p_ref.grad = grad.clone()
        opt.step()
        tp.foreach_add_([step], 1)
        tp.FUSED_ADAM([p_ours], [grad], [m1], [m2], [], [step], amsgrad=False, lr=1e-2, beta1=0.9, beta2=0.999,
                      weight_decay=0.0, eps=1e-8, maximize=False, grad_scale=None, found_inf=None)
    torch.testing.assert_close(p_ours, p_ref.detach())
    torch.testing.assert_close(m1, opt.state[p_ref]["exp_avg"])


def test_foreach_lerp_and_add() -> None:
    a, b = [torch.ones(3), torch.zeros(2)], [torch.full((3,), 3.0), torch.full((2,), 2.0)]
    tp.foreach_lerp_(a, b, 0.25)
    torch.testing.assert_close(a[0], torch.full((3,), 1.5))
    torch.testing.assert_close(a[1], torch.full((2,), 0.5))
    tp.foreach_add_(a, 1.0)
    torch.testing.assert_close(a[1], torch.full((2,), 1.5))


def test_relu_backward_is_relus_gradient() -> None:
    x = torch.randn(5, 4, requires_grad=True)
    y = F.relu(x)
    g = torch.randn(5, 4)
    y.backward(g)
    torch.testing.assert_close(tp.relu_backward(g, y.detach()), x.grad)
    out = g.clone()
    assert tp.relu_backward(out, y.detach(), out=out) is out
    torch.testing.assert_close(out, x.grad)


@pytest.mark.skipif(not tp.onednn_linear_available(), reason="this build has no oneDNN linear primitive")
@pytest.mark.parametrize("relu", [False, True])
def test_onednn_linear_is_linear(relu: bool) -> None:
    torch.manual_seed(1)
    a, w, b = torch.randn(6, 5), torch.randn(4, 5), torch.randn(4)
    ref = F.linear(a, w, b)
    torch.testing.assert_close(tp.onednn_linear(a, w, b, relu), ref.relu() if relu else ref, rtol=1e-5, atol=1e-5)


def test_optimizer_hooks_are_seen() -> None:
    opt = torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    assert not tp.optimizer_has_hooks(opt)
    handle = opt.register_step_pre_hook(lambda *args: None)
    assert tp.optimizer_has_hooks(opt)
    handle.remove()
    from torch.optim.optimizer import register_optimizer_step_post_hook

    handle = register_optimizer_step_post_hook(lambda *args: None)
    try:
        assert tp.optimizer_has_hooks(opt)
    finally:
        handle.remove()
    assert not tp.optimizer_has_hooks(opt)
