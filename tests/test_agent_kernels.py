"""The autograd-free training kernels of the agents must give autograd's gradients."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mira.agents import gemm
from mira.agents.networks import (
    EnsembleQ,
    EnsembleQKernels,
    MLPKernels,
    SquashedGaussianActor,
    relu_mlp,
    squashed_gaussian_backward,
    squashed_gaussian_forward,
)
from mira.errors import UsageError


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


def _backends() -> list[str]:
    has = bool(torch.backends.mkldnn.is_available()) and hasattr(torch.ops.mkldnn, "_linear_pointwise")
    return ["blas", "onednn"] if has else ["blas"]


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 40), k=st.integers(1, 40), m=st.integers(1, 40), e=st.integers(1, 3),
       trans_a=st.booleans(), trans_b=st.booleans(), with_bias=st.booleans(), relu=st.booleans(),
       seed=st.integers(0, 2**16))
def test_gemm_products_match_torch_on_every_backend(n: int, k: int, m: int, e: int, trans_a: bool, trans_b: bool,
                                                    with_bias: bool, relu: bool, seed: int) -> None:
    """The kernels' products (transposed views, fused bias and ReLU, ``out=`` buffers) on each backend."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(e, k, n, generator=g).transpose(1, 2) if trans_a else torch.randn(e, n, k, generator=g)
    b = torch.randn(e, m, k, generator=g).transpose(1, 2) if trans_b else torch.randn(e, k, m, generator=g)
    bias = torch.randn(e, 1, m, generator=g) if with_bias else None
    want = a @ b + (bias if bias is not None else 0.0)
    want = want.relu() if relu else want
    saved = gemm.BACKEND
    try:
        for backend in _backends():
            gemm.BACKEND = backend
            out = torch.full((e, n, m), float("nan"))
            got = gemm.bmm(a, b, bias, relu, out=out)
            assert got is out
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
            single = gemm.matmul(a[0], b[0], None if bias is None else bias[0, 0], relu)
            torch.testing.assert_close(single, want[0], rtol=1e-5, atol=1e-5)
    finally:
        gemm.BACKEND = saved


def test_gemm_backend_choice_is_checked() -> None:
    with pytest.raises(UsageError, match="MIRA_GEMM"):
        gemm._resolve("fast")
    assert gemm._resolve("blas") == "blas"
    assert gemm._resolve("auto") in ("blas", "onednn")
