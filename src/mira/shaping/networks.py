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
* :class:`ValuePotential` (φ): a two-hidden-layer MLP from v to the scalar potential Φ(s) (the paper's
  optional state projection beside v is not used: the state reaches Φ through the query).

The sizes are Table 1's where it gives them (d_z, the TCE's and the VPM's widths), otherwise small:
the networks see a handful of factors.

The per-factor embedder is written so the factor axis costs no Python loop: the ID and metadata of
the K factors are mapped once per forward to a per-factor scale and shift ``(a_k, c_k)``, and every
(state, factor) pair is then ``z = W_2 SiLU(x · a_k + c_k) + b_2``. Because ``W_2`` is linear, the
forward never forms ``z``: scores and pooling act on the hidden layer and ``W_2`` is applied once to
the pooled vector (see ``FactorAttentionBlock.forward``; ``reference`` is the literal definition).
"""

from __future__ import annotations

import copy
import math
from typing import cast

import torch
from torch import nn
from torch.nn import functional as F

from mira.agents import gemm
from mira.shaping.factors import META_DIM

D_Z = 64
"""Factor embedding dimension d_z of the FAB (Table 1); also the TCE's input and output."""
ID_DIM = 16
"""Dimension of the learned per-name factor-ID embedding: enough to tell a few dozen names apart."""
ID_SLOTS = 64
"""Initial rows of the name → ID-embedding table (doubled when a fresh FAB needs more)."""
FAB_HIDDEN = 64
"""Hidden width of the per-factor embedder g_ϕ: one scalar value per factor goes in."""
QUERY_HIDDEN = 64
"""Hidden width of the state query Q_ϕ(s)."""
TCE_HIDDEN = 128
"""GRU hidden size of the Temporal Context Encoder (Table 1)."""
VPM_HIDDEN = 128
"""Width of the two hidden layers of the Value Potential Mapping MLP (Table 1)."""


class FactorAttentionBlock(nn.Module):
    """FAB (ϕ): factor embedder g_ϕ, ID table, state query Q_ϕ and bilinear attention W_ϕ."""

    def __init__(self, obs_dim: int, *, d_z: int = D_Z, id_dim: int = ID_DIM, id_slots: int = ID_SLOTS,
                 hidden: int = FAB_HIDDEN, query_hidden: int = QUERY_HIDDEN, meta_dim: int = META_DIM) -> None:
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

    def hidden_embed(self, x: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor) -> torch.Tensor:
        """``h [B, K, H]``: the embedder's hidden layer ``SiLU(x · a_k + c_k)``, before ``W_2``."""
        return self._hidden_kbh(x, ids, meta).transpose(0, 1)

    def _hidden_kbh(self, x: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor) -> torch.Tensor:
        """The same hidden layer factor-major, ``[K, B, H]`` (see :meth:`forward`)."""
        ctx = self.factor_ctx(torch.cat([ids, meta], dim=-1))  # [K, 2H]
        scale, shift = ctx[:, : self.hidden], ctx[:, self.hidden :]
        return F.silu(torch.addcmul(shift.unsqueeze(1), x.t().contiguous().unsqueeze(-1), scale.unsqueeze(1)))

    def embed(self, x: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor) -> torch.Tensor:
        """``z [B, K, d_z]`` from normalised values ``x [B, K]``, ``ids [K, id_dim]``, ``meta [K, M]``."""
        return self.factor_out(self.hidden_embed(x, ids, meta))

    def query_hidden(self, obs: torch.Tensor) -> torch.Tensor:
        """``y [B, query_hidden]``: the state query's hidden layer (``q = W_q y + b_q``)."""
        return self.query[2](self.query[1](self.query[0](obs)))

    def score_map(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(A, a0)`` with ``qᵀ W_ϕ z_i / √d_z = h_i · (y A + a0) + c(s)`` for ``z_i = W_2 h_i + b_2``.

        ``y`` is the query's last hidden layer (``q = W_q y + b_q``) and ``c(s) = qᵀ W_ϕ b_2 / √d_z`` is
        the same for every factor of a state, so softmax ignores it. Folding ``W_q``, ``W_ϕ`` and
        ``W_2`` into one ``[query_hidden, hidden]`` map is what lets the forward skip embedding every
        (state, factor) pair through ``W_2``: the scores and the pooling both work on ``h_i`` directly.
        """
        last = cast(nn.Linear, self.query[-1])
        w = self.w_attn @ self.factor_out.weight / math.sqrt(self.d_z)  # [d_z, H]
        return last.weight.t() @ w, last.bias @ w

    def forward(self, x: torch.Tensor, obs: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor,
                mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns ``v [B, d_z]`` and ``α [B, K]``.

        ``obs`` is the (normalised) state ``[B, obs_dim]``; ``mask`` (``[K]`` or ``[B, K]``, True =
        present) removes factors: their α is exactly 0 and the others renormalise among themselves.

        Computed without materialising ``z [B, K, d_z]`` (the definition is :meth:`reference`): with
        ``z_i = W_2 h_i + b_2``, the scores are ``h_i · g(s)`` up to a per-state constant (see
        :meth:`score_map`) and ``v = Σ α_i z_i = W_2 (Σ α_i h_i) + (Σ α_i) b_2``. This is the same
        function with K times fewer multiply-adds in the embedder, forward and backward.
        """
        # Factor-major layout [K, B, H]: the softmax and the pooling then run across the factor axis
        # over contiguous [B]- and [B, H]-slabs, several times faster on CPU than over a trailing axis
        # of a few factors.
        h = self._hidden_kbh(x, ids, meta)  # [K, B, H]
        a_map, a_bias = self.score_map()
        g = torch.addmm(a_bias, self.query_hidden(obs), a_map)  # [B, H]
        scores = (h * g).sum(-1)  # [K, B]
        if mask is not None:
            mask = mask.expand(x.shape).t()  # [K, B]
            scores = scores.masked_fill(~mask, float("-inf"))
            alpha = torch.softmax(scores, dim=0)
            # A row with every factor masked has no attention at all (softmax would give NaN).
            alpha = torch.where(mask, alpha, torch.zeros((), dtype=alpha.dtype, device=alpha.device))
            weight = alpha.sum(0).unsqueeze(-1)  # 1, or 0 for a row with nothing present
        else:
            alpha = torch.softmax(scores, dim=0)
            weight = None
        pooled = (alpha.unsqueeze(-1) * h).sum(0)  # Σ α_i h_i, [B, H]
        out = self.factor_out
        if weight is None:
            v = F.linear(pooled, out.weight, out.bias if alpha.shape[0] else None)
        else:
            v = torch.addmm(weight * out.bias, pooled, out.weight.t())
        alpha = alpha.t()  # [B, K]
        return v, alpha

    def reference(self, x: torch.Tensor, obs: torch.Tensor, ids: torch.Tensor, meta: torch.Tensor,
                  mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The FAB as the paper writes it, ``(v, α, z)``: every ``z_i`` embedded, ``α = softmax(qᵀ W_ϕ z / √d_z)``,
        ``v = Σ α_i z_i``. :meth:`forward` computes the same ``v`` and ``α`` faster (tests check both agree)."""
        z = self.embed(x, ids, meta)
        u = self.query(obs) @ self.w_attn
        scores = (z * u.unsqueeze(1)).sum(-1) / math.sqrt(self.d_z)
        if mask is not None:
            mask = mask.expand_as(scores)
            alpha = torch.softmax(scores.masked_fill(~mask, float("-inf")), dim=-1)
            alpha = torch.where(mask, alpha, torch.zeros((), dtype=alpha.dtype, device=alpha.device))
        else:
            alpha = torch.softmax(scores, dim=-1)
        return (alpha.unsqueeze(-1) * z).sum(1), alpha, z


def attention_entropy(alpha: torch.Tensor) -> torch.Tensor:
    """Shannon entropy (nats) of each row of α ``[B, K]`` (masked zeros contribute nothing)."""
    return -(alpha * torch.log(alpha.clamp_min(1e-12))).sum(-1)


class ValuePotential(nn.Module):
    """VPM (φ): ``Φ(s) = MLP(v)`` with two hidden layers (ReLU)."""

    def __init__(self, d_z: int = D_Z, *, hidden: int = VPM_HIDDEN) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(d_z, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1))

    def forward(self, v: torch.Tensor) -> torch.Tensor:
        first, second, out = self.mlp[0], self.mlp[2], cast(nn.Linear, self.mlp[4])
        h = F.relu(second(F.relu(first(v))))
        # The width-1 output layer as a matrix-vector product: a GEMM with one output column is
        # several times slower on CPU BLAS than the GEMV it really is.
        return torch.mv(h, out.weight[0]) + out.bias


def _transposed_copy(w: torch.Tensor) -> torch.Tensor:
    """``wᵀ`` as a new contiguous tensor (``.contiguous()`` would return ``w`` itself for a vector)."""
    return w.detach().t().clone(memory_format=torch.contiguous_format)


class FrozenPotential:
    """Φ(s) = ``unit · vpm(fab(x, o, ids, meta)[0])`` from *raw* factor values ``f`` and states ``obs``,
    with ``x = clamp(f · f_inv + f_shift, ±clip)`` and likewise ``o``: the shaping of sampled batches,
    without a gradient, with every parameter-only product precomputed.

    Built once per parameter version (the caller rebuilds it after each optimiser step), it holds the
    per-factor scale and shift of the embedder's hidden layer for these ``ids`` and ``meta``, the
    folded score map (:meth:`FactorAttentionBlock.score_map`), the FAB's output layer ``W_2`` folded
    into the VPM's first layer (``V_1 v = (V_1 W_2) Σ α_i h_i + (Σ α_i) V_1 b_2``) and ``unit`` folded
    into the output layer. A call is then about twenty tensor ops on the batch, activations in place.
    At these sizes dispatch and cold caches (the agent's update runs between two calls and evicts
    everything) cost more than the arithmetic, so the count of ops is what this keeps small.
    """

    @torch.no_grad()
    def __init__(self, fab: FactorAttentionBlock, vpm: ValuePotential, ids: torch.Tensor, meta: torch.Tensor, *,
                 f_shift: torch.Tensor | None = None, f_inv: torch.Tensor | None = None,
                 o_shift: torch.Tensor | None = None, o_inv: torch.Tensor | None = None,
                 clip: float = math.inf, unit: float = 1.0) -> None:
        self.k = int(ids.shape[0])
        self.exact = self.k == 0  # no factors: the modules' own forward (v = 0)
        # Copies, like every tensor below: the modules may be trained (on another thread) while this
        # keeps evaluating the potential they had when it was built.
        self.modules = (copy.deepcopy(fab), copy.deepcopy(vpm)) if self.exact else None
        self.ids, self.meta, self.unit, self.clip = ids, meta, float(unit), float(clip)
        self.f_affine = None if f_inv is None or f_shift is None else (f_shift, f_inv)
        self.o_affine = None if o_inv is None or o_shift is None else (o_shift, o_inv)
        if self.exact:
            return
        ctx = fab.factor_ctx(torch.cat([ids, meta], dim=-1))  # [K, 2H]
        self.scale = ctx[:, : fab.hidden].unsqueeze(1).contiguous()  # [K, 1, H]
        self.shift = ctx[:, fab.hidden :].unsqueeze(1).contiguous()
        q_in, q_norm = cast(nn.Linear, fab.query[0]), cast(nn.LayerNorm, fab.query[1])
        self.q_weight_t, self.q_bias = _transposed_copy(q_in.weight), q_in.bias.detach().clone()
        self.ln = (q_norm.normalized_shape, q_norm.weight.detach().clone(), q_norm.bias.detach().clone(), q_norm.eps)
        a_map, self.a_bias = fab.score_map()
        self.a_map = a_map.contiguous()
        first, second, out = (cast(nn.Linear, vpm.mlp[i]) for i in (0, 2, 4))
        w_out = fab.factor_out.weight
        self.v1_weight_t = (first.weight @ w_out).t().contiguous()  # [H, hidden]
        self.v1_bias = torch.addmv(first.bias, first.weight, fab.factor_out.bias)
        self.v2_weight_t, self.v2_bias = _transposed_copy(second.weight), second.bias.detach().clone()
        self.v3_weight, self.v3_bias = out.weight[0] * self.unit, out.bias * self.unit

    def _inputs(self, f: torch.Tensor, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = self.clip
        x = f if self.f_affine is None else torch.addcmul(self.f_affine[0], f, self.f_affine[1]).clamp_(-c, c)
        o = obs if self.o_affine is None else torch.addcmul(self.o_affine[0], obs, self.o_affine[1]).clamp_(-c, c)
        return x, o

    @torch.no_grad()
    def __call__(self, f: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """Φ ``[B]`` from factor values ``f [B, K]`` and states ``obs [B, obs_dim]``."""
        x, o = self._inputs(f, obs)
        if self.exact:
            assert self.modules is not None
            fab_copy, vpm_copy = self.modules
            return vpm_copy(fab_copy(x, o, self.ids, self.meta)[0]) * self.unit
        # Factor-major [K, B, H], as in FactorAttentionBlock.forward; x made contiguous first (the
        # broadcast multiply-add reads a transposed [B, K] operand at half speed).
        h = F.silu(torch.addcmul(self.shift, x.t().contiguous().unsqueeze(-1), self.scale), inplace=True)
        y = F.layer_norm(gemm.matmul(o, self.q_weight_t, self.q_bias), *self.ln)
        g = gemm.matmul(F.silu(y, inplace=True), self.a_map, self.a_bias)  # [B, H]
        alpha = torch.softmax((h * g).sum(-1), dim=0).unsqueeze(-1)  # [K, B, 1]
        # Σ α_i h_i as K multiply-adds of [B, H] slabs: faster than a product and a reduction over K.
        pooled = torch.mul(h[0], alpha[0])
        for i in range(1, self.k):
            pooled.addcmul_(h[i], alpha[i])
        hid = gemm.matmul(pooled, self.v1_weight_t, self.v1_bias, relu=True)
        hid = gemm.matmul(hid, self.v2_weight_t, self.v2_bias, relu=True)
        return torch.addmv(self.v3_bias, hid, self.v3_weight)


class TemporalContextEncoder(nn.Module):
    """TCE (ψ): a GRU over the previous aggregations of the episode that predicts the current one."""

    def __init__(self, d_z: int = D_Z, *, hidden: int = TCE_HIDDEN) -> None:
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
