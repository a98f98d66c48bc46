"""HARS networks (section 4.2.2, Figure 2): FAB (ϕ), TCE (ψ) and VPM (φ).

* :class:`FactorAttentionBlock` (ϕ): ``z_i = g_ϕ(x_i, ID_i, meta_i) ∈ R^{d_z}`` for every PHI factor
  ``i`` (``x_i`` its normalised value), a state query ``q = Q_ϕ(s)``, single-head bilinear attention
  ``α_i = softmax_i(qᵀ W_ϕ z_i / √d_z)`` over the factors present (a boolean mask removes absent
  ones: a masked factor is exactly as if it were not there) and the pooled ``v = Σ_i α_i z_i``.
  Factors are a *set*: nothing depends on their order, only on their names (the ID embedding is a
  row of a table looked up through a name → slot map kept by the caller). The same compiled module
  handles any K, including K = 0 (then α is empty and v = 0).
* :class:`TemporalContextEncoder` (ψ): a GRU over the ``W − 1`` previous aggregations of the same
  episode, predicting the current one, ``v̂_t``. It is an auxiliary regulariser; it never feeds Φ.
* :class:`ValuePotential` (φ): a two-hidden-layer MLP from v (optionally concatenated with a learned
  state projection) to the scalar potential Φ(s).

The per-factor embedder is written so the factor axis costs no Python loop: the ID and metadata of
the K factors are mapped once per forward to a per-factor scale and shift ``(a_k, c_k)``, and every
(state, factor) pair is then ``W_2 SiLU(x · a_k + c_k) + b_2`` — one broadcast and one matmul.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from mira.shaping.factors import META_DIM


class FactorAttentionBlock(nn.Module):
    """FAB (ϕ): factor embedder g_ϕ, ID table, state query Q_ϕ and bilinear attention W_ϕ."""

    def __init__(self, obs_dim: int, *, d_z: int = 64, id_dim: int = 16, id_slots: int = 64, hidden: int = 64,
                 query_hidden: int = 128, meta_dim: int = META_DIM) -> None:
        super().__init__()
        self.d_z, self.id_dim, self.hidden = d_z, id_dim, hidden
        self.id_table = nn.Parameter(torch.zeros(id_slots, id_dim))
        self.factor_ctx = nn.Linear(id_dim + meta_dim, 2 * hidden)
        self.factor_out = nn.Linear(hidden, d_z)
        self.query = nn.Sequential(nn.Linear(obs_dim, query_hidden), nn.LayerNorm(query_hidden), nn.SiLU(),
                                   nn.Linear(query_hidden, d_z))
        self.w_attn = nn.Parameter(torch.randn(d_z, d_z) / math.sqrt(d_z))

    @property
    def id_slots(self) -> int:
        return int(self.id_table.shape[0])

    def ids(self, slots: torch.Tensor) -> torch.Tensor:
        """ID embeddings ``[K, id_dim]`` of the factors in ``slots`` (``[K]`` long)."""
        return self.id_table.index_select(0, slots)

    def embed(self, x: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor) -> torch.Tensor:
        """``z [B, K, d_z]`` from normalised values ``x [B, K]``, ``ids [K, id_dim]``, ``meta [K, M]``."""
        ctx = self.factor_ctx(torch.cat([ids, meta], dim=-1))  # [K, 2H]
        scale, shift = ctx[:, : self.hidden], ctx[:, self.hidden :]
        h = F.silu(x.unsqueeze(-1) * scale + shift)  # [B, K, H]
        return self.factor_out(h)

    def forward(self, x: torch.Tensor, obs: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor,
                mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns ``v [B, d_z]``, ``α [B, K]`` and ``z [B, K, d_z]``.

        ``obs`` is the (normalised) state ``[B, obs_dim]``; ``mask`` (``[K]`` or ``[B, K]``, True =
        present) removes factors: their α is exactly 0 and the others renormalise among themselves.
        """
        z = self.embed(x, ids, meta)
        q = self.query(obs)  # [B, d_z]
        u = q @ self.w_attn  # [B, d_z]
        # Elementwise products, not einsum/bmm: K is small and batched tiny matmuls are slow on CPU.
        scores = (z * u.unsqueeze(1)).sum(-1) / math.sqrt(self.d_z)
        if mask is not None:
            mask = mask.expand_as(scores)
            scores = scores.masked_fill(~mask, float("-inf"))
            alpha = torch.softmax(scores, dim=-1)
            # A row with every factor masked has no attention at all (softmax would give NaN).
            alpha = torch.where(mask, alpha, torch.zeros((), dtype=alpha.dtype, device=alpha.device))
        else:
            alpha = torch.softmax(scores, dim=-1)
        v = (alpha.unsqueeze(-1) * z).sum(1)
        return v, alpha, z


def attention_entropy(alpha: torch.Tensor) -> torch.Tensor:
    """Shannon entropy (nats) of each row of α ``[B, K]`` (masked zeros contribute nothing)."""
    return -(alpha * torch.log(alpha.clamp_min(1e-12))).sum(-1)


class ValuePotential(nn.Module):
    """VPM (φ): ``Φ(s) = MLP([v ; P(s)])`` with two hidden layers (ReLU)."""

    def __init__(self, d_z: int, obs_dim: int, *, hidden: int = 128, state_proj: bool = False,
                 state_proj_dim: int = 32) -> None:
        super().__init__()
        self.state_proj = nn.Linear(obs_dim, state_proj_dim) if state_proj else None
        in_dim = d_z + (state_proj_dim if state_proj else 0)
        self.mlp = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1))

    def forward(self, v: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        if self.state_proj is not None:
            v = torch.cat([v, torch.tanh(self.state_proj(obs))], dim=-1)
        return self.mlp(v).squeeze(-1)


class TemporalContextEncoder(nn.Module):
    """TCE (ψ): a GRU over the previous aggregations of the episode that predicts the current one."""

    def __init__(self, d_z: int, *, hidden: int = 128) -> None:
        super().__init__()
        self.gru = nn.GRU(d_z, hidden, batch_first=True)
        self.head = nn.Linear(hidden, d_z)
        self.hidden = hidden

    def forward(self, context: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """``v̂ [N, d_z]`` from ``context [N, L, d_z]`` (oldest first) and ``valid [N, L]``.

        Windows arrive left-padded (positions before the episode started are invalid, so the valid
        ones are a suffix). They are shifted to start at position 0 and the GRU's output is read at
        each row's last valid position, so padding never enters a prediction; a row with no valid
        position gets the prediction of an empty history (callers mask it out of the loss).
        """
        n, length = valid.shape
        count = valid.sum(1)  # [N]
        pos = torch.arange(length, device=valid.device)
        src = (pos.unsqueeze(0) + (length - count).unsqueeze(1)).clamp_max(length - 1)  # [N, L]
        aligned = context.gather(1, src.unsqueeze(-1).expand(-1, -1, context.shape[-1]))
        out, _ = self.gru(aligned)  # [N, L, H]
        last = (count - 1).clamp_min(0)
        h = out[torch.arange(n, device=valid.device), last]
        h = torch.where((count > 0).unsqueeze(1), h, torch.zeros((), dtype=h.dtype, device=h.device))
        return self.head(h)
