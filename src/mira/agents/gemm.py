"""Dense matrix products of the autograd-free update kernels.

Two backends compute them: PyTorch's BLAS (``torch.addmm``) and the oneDNN linear primitive PyTorch
also ships, which picks its kernels from the CPU's instruction set (on some CPUs the BLAS does not use
the widest vector units). The results are the same products up to
float rounding.

The backend is chosen once per process: ``MIRA_GEMM=onednn`` or ``blas``, default ``auto`` (oneDNN
whenever PyTorch exposes it). Only float32 CPU tensors take the oneDNN path; everything else (float64
in the tests, CUDA) goes through the usual ``torch.addmm``. A run records the backend it used, since
two backends round differently and a rerun should use the same one.
"""

from __future__ import annotations

import os

import torch

from mira.agents.torch_private import onednn_linear, onednn_linear_available
from mira.errors import UsageError

_CHOICES = ("auto", "onednn", "blas")


def _resolve(choice: str) -> str:
    if choice not in _CHOICES:
        raise UsageError(f"environment variable MIRA_GEMM={choice!r}: expected one of {', '.join(_CHOICES)}")
    has_onednn = onednn_linear_available()
    if choice == "onednn" and not has_onednn:
        raise UsageError("environment variable MIRA_GEMM=onednn: this PyTorch build has no oneDNN linear primitive")
    return "onednn" if choice != "blas" and has_onednn else "blas"


BACKEND: str | None = None
"""``"onednn"`` or ``"blas"`` once :func:`backend` has read ``MIRA_GEMM`` (None before)."""


def backend() -> str:
    """How :func:`matmul` multiplies float32 CPU matrices in this process (read from ``MIRA_GEMM`` once)."""
    global BACKEND
    if BACKEND is None:
        BACKEND = _resolve(os.environ.get("MIRA_GEMM", "auto"))
    return BACKEND


def matmul(a: torch.Tensor, b: torch.Tensor, bias: torch.Tensor | None = None, relu: bool = False,
           out: torch.Tensor | None = None) -> torch.Tensor:
    """``relu?(a @ b + bias)`` for ``a [n, k]``, ``b [k, m]`` (either may be a transposed view) and
    ``bias [m]``, written into ``out`` when given (then returned)."""
    if (BACKEND or backend()) == "onednn" and a.dtype == torch.float32 and a.device.type == "cpu":
        # The primitive computes a @ wᵀ + bias for a weight w [m, k]: bᵀ is that weight, as a view.
        res = onednn_linear(a, b.t(), bias, relu)
        return res if out is None else out.copy_(res)
    if bias is None:
        res = torch.mm(a, b) if out is None else torch.mm(a, b, out=out)
    else:
        res = torch.addmm(bias, a, b) if out is None else torch.addmm(bias, a, b, out=out)
    return res.relu_() if relu else res


def bmm(a: torch.Tensor, b: torch.Tensor, bias: torch.Tensor | None = None, relu: bool = False,
        out: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`matmul` for every member of an ensemble: ``a [E, n, k]``, ``b [E, k, m]``, ``bias [E, 1, m]``.

    oneDNN has no batched primitive here, so its path runs one product per member (E is 1 or 2) and
    copies it into ``out``; the BLAS path is one ``baddbmm``/``bmm``.
    """
    if (BACKEND or backend()) == "onednn" and a.dtype == torch.float32 and a.device.type == "cpu":
        if out is None:
            out = a.new_empty(a.shape[0], a.shape[1], b.shape[2])
        for m in range(a.shape[0]):
            matmul(a[m], b[m], None if bias is None else bias[m, 0], relu, out=out[m])
        return out
    if bias is None:
        res = torch.bmm(a, b) if out is None else torch.bmm(a, b, out=out)
    else:
        res = torch.baddbmm(bias, a, b) if out is None else torch.baddbmm(bias, a, b, out=out)
    return res.relu_() if relu else res


__all__ = ["BACKEND", "backend", "bmm", "matmul"]
