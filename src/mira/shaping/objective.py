"""HARS's objective (eq. 10 without the critic's term): what (ϕ, φ, ψ) minimise, on one screen.

    L = λ · L_align + μ · L_aux − β · H(α)

* ``L_align`` (eq. 11): the TD loss ``(Φ(s) − (r + γ(1 − d)Φ(s′)))²`` with the target side stopped,
  plus ``η · E[Φ(s_T)²]`` over true terminal states. ``r`` is the reward Φ is aligned to: the
  decomposition head's r̂ by default, the episodic r_ext under ``hars.alignment=episodic``. Both
  terms are measured in units of σ_R (``unit``), so they weigh the same on every task.
* ``L_aux``: the TCE's ``‖v_t − v̂_t‖²`` with the target v_t stopped (otherwise the cheapest way to
  lower it would be to make v constant), over windows that have a past in the same episode.
* ``H(α)``: the attention entropy, maximised against premature collapse onto one factor.

The joint term ⟨∂L_RL/∂Φ, Φ⟩ and the optimiser step belong to the caller (:mod:`mira.shaping.source`),
as does deciding when to compute L_aux. The decomposition head is not trained here: it is a closed-form
fit to episodic returns (:mod:`mira.shaping.decomposition`), and nothing here reaches it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mira.shaping.networks import TemporalContextEncoder, attention_entropy

ALIGN_WEIGHT = 1.0
"""λ of eq. (10), the weight of L_align (Table 1)."""
AUX_WEIGHT = 0.1
"""μ of eq. (10), the weight of the TCE's L_aux (Table 1)."""
TERMINAL_WEIGHT = 0.1
"""η of eq. (11), the penalty η·E[Φ(s_T)²] on true terminal states (the paper only asks η > 0)."""
ENTROPY_WEIGHT = 1e-3
"""β, the weight of the attention entropy bonus: small, it only keeps α from collapsing onto one factor
early."""


@dataclass
class ObjectiveTerms:
    """The objective's value and its parts (``loss`` carries the graph; the parts are for the log)."""

    loss: torch.Tensor
    l_align: torch.Tensor
    l_td: torch.Tensor
    """The TD part of L_align, in units of σ_R²."""
    l_aux: torch.Tensor
    entropy: torch.Tensor
    target: torch.Tensor
    """The (stopped) TD target ``r + γ(1 − d)Φ(s′)`` ``[B]``, in reward units."""


def alignment_loss(phi_s: torch.Tensor, phi_next: torch.Tensor, reward: torch.Tensor, terminated: torch.Tensor,
                   gamma: float, unit: float, terminal_weight: float
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(L_align, L_td, target)`` of eq. (11) for Φ over a batch's s and s′."""
    target = (reward + gamma * (1.0 - terminated) * phi_next).detach()
    td = (phi_s - target) / unit
    l_td = td.pow(2).mean()
    l_term = (terminated * (phi_next / unit).pow(2)).sum() / terminated.sum().clamp_min(1.0)
    return l_td + terminal_weight * l_term, l_td, target


def temporal_loss(tce: TemporalContextEncoder, v: torch.Tensor, v_ctx: torch.Tensor | None,
                  ctx_valid: torch.Tensor | None) -> torch.Tensor:
    """L_aux: the TCE's squared error predicting the first ``len(v_ctx)`` rows of ``v`` from their past."""
    if v_ctx is None or ctx_valid is None or v_ctx.shape[0] == 0:
        return v.new_zeros(())
    n = v_ctx.shape[0]
    pred = tce(v_ctx, ctx_valid)
    err = (pred - v[:n].detach()).pow(2).sum(-1)
    has_past = ctx_valid[:, -1].to(err.dtype)
    return (err * has_past).sum() / has_past.sum().clamp_min(1.0)


def hars_objective(tce: TemporalContextEncoder, *, phi: torch.Tensor, v: torch.Tensor,
                   alpha: torch.Tensor, v_ctx: torch.Tensor | None, ctx_valid: torch.Tensor | None,
                   reward: torch.Tensor, terminated: torch.Tensor, gamma: float, unit: float) -> ObjectiveTerms:
    """The objective on one batch from the forward over its ``[s; s′]`` (``phi``, ``v``, ``alpha`` are
    ``[2B]``, ``[2B, d_z]``, ``[2B, K]``) and the TCE windows of its first rows (``v_ctx``)."""
    b = reward.shape[0]
    l_align, l_td, target = alignment_loss(phi[:b], phi[b:], reward, terminated, gamma, unit, TERMINAL_WEIGHT)
    entropy = attention_entropy(alpha).mean()
    l_aux = temporal_loss(tce, v, v_ctx, ctx_valid)
    loss = ALIGN_WEIGHT * l_align + AUX_WEIGHT * l_aux - ENTROPY_WEIGHT * entropy
    return ObjectiveTerms(loss, l_align, l_td, l_aux, entropy, target)
