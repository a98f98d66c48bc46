"""The autograd-free training kernels of the agents must give autograd's gradients."""

from __future__ import annotations

import torch

from mira.agents.networks import (
    EnsembleQ,
    EnsembleQKernels,
    MLPKernels,
    SquashedGaussianActor,
    relu_mlp,
    squashed_gaussian_backward,
    squashed_gaussian_forward,
)


def test_ensemble_q_kernels_match_autograd() -> None:
    torch.manual_seed(0)
    critic = EnsembleQ(2, 5, 3, (16, 16))
    params = critic.params()
    x = torch.randn(9, 8)
    dq = torch.randn(2, 9)
    kernels = EnsembleQKernels(critic)
    with torch.no_grad():
        q = kernels.forward(params, x).clone()
        grads = [torch.zeros_like(p) for p in params]
        kernels.backward(params, dq, grads)
    ref_q = critic(x[:, :5], x[:, 5:])
    assert torch.allclose(q, ref_q, atol=1e-5)
    ref = torch.autograd.grad((ref_q * dq).sum(), params)
    for g, r in zip(grads, ref, strict=True):
        assert torch.allclose(g, r, atol=1e-5), (g - r).abs().max()


def test_mlp_kernels_and_squashed_gaussian_match_autograd() -> None:
    torch.manual_seed(1)
    actor = SquashedGaussianActor(6, 3, (16, 16))
    params = actor.params()
    x = torch.randn(11, 6)
    noise = torch.randn(11, 3)
    g_action, g_logp = torch.randn(11, 3), torch.randn(11)
    kernels = MLPKernels(params)
    with torch.no_grad():
        out = kernels.forward(params, x)
        action, logp, saved = squashed_gaussian_forward(out, noise)
        action, logp = action.clone(), logp.clone()
        g_out = squashed_gaussian_backward(saved, g_action, g_logp)
        grads = [torch.zeros_like(p) for p in params]
        kernels.backward(params, g_out, grads)
    ref_out = relu_mlp(params, x)
    ref_action, ref_logp, _ = squashed_gaussian_forward(ref_out, noise)
    assert torch.allclose(action, ref_action, atol=1e-5) and torch.allclose(logp, ref_logp, atol=1e-4)
    ref = torch.autograd.grad((ref_action * g_action).sum() + (ref_logp * g_logp).sum(), params)
    for g, r in zip(grads, ref, strict=True):
        assert torch.allclose(g, r, atol=1e-4), (g - r).abs().max()
