"""HARS as a reward source: the decomposed reward r̂ and a learned potential Φ over the program's factors.

What the agent learns from, for a sampled transition (s, a, s′):

    r = r̂(s, a, s′) + κ · (γ · Φ(s′) · (1 − terminated) − Φ(s)),

with r̂ the decomposition head's per-step reward (:mod:`mira.shaping.decomposition`, fitted to
episodic returns only) and Φ the FAB → VPM potential TD-aligned to r̂ (:mod:`mira.shaping.objective`).
κ = 1 by default (0 gives the agent r̂ alone); under ``hars.alignment=episodic`` (the paper's letter)
r̂ is replaced by the episodic r_ext in both places. Terminals are absorbing; a time-limit truncation
keeps Φ(s′), as the critic keeps bootstrapping. The pieces:

* :mod:`mira.shaping.columns`: each stored transition's factor values, evaluated lazily in batches;
* :mod:`mira.shaping.decomposition`: r̂ and its weights, the section-3 evidence MCM/SRR read;
* :mod:`mira.shaping.objective`: λ L_align + μ L_aux − β H(α), on one screen;
* :mod:`mira.shaping.networks`: FAB (ϕ), VPM (φ), TCE (ψ); ``FactorAttentionBlock.reference`` is the
  plain definition, ``forward`` and :class:`FrozenPotential` the fast paths (tests check they agree);
* this module: relabelling, the training schedule, program changes, checkpoints.

Training schedule (speed, not method). Φ changes only when a HARS training step lands: its weights
and the input statistics and σ_R it reads are one fixed function from one training update to the next,
so the trainer hands a whole cycle's batches over together (``lookahead`` / ``relabel_many``) when the
training batch is due: that batch is shaped with a graph, the others by a :class:`FrozenPotential`
built once, in one forward pass. The step taken on a cycle's training batch lands at the next cycle's
training batch (or when Φ is read earlier: the monitor, a checkpoint, a program change; see ``sync``),
which is what lets ``train_in_background`` run it, and the cycle's no-grad shaping pass, on a second
thread while the agent updates. Where the step runs changes nothing in the computation
(``tests/test_shaping_e2e.py`` checks bit for bit). r̂ changes only at episode ends (``revision``).

Joint objective (eq. 10). With ``joint=True`` and κ ≠ 0 the reward handed to the agent carries gradient
into (ϕ, φ): the critic's TD loss L_RL is minimised over the shaping parameters as well. Rather than
letting the agent's ``backward`` walk the HARS graph, the reward is built from a detached leaf copy of
Φ; the agent's backward deposits ∂L_RL/∂Φ on that leaf, and the training step backpropagates
``objective + ⟨∂L_RL/∂Φ, Φ⟩`` through the HARS graph once: by the chain rule exactly the gradient of
``L_RL + objective`` w.r.t. (ϕ, φ, ψ). The decomposition head is never trained by either loss.

A structural edit (``set_program``, section 4.4.5) re-initialises ϕ and φ and their optimiser state,
keeps ψ (and its optimiser state) and never touches the agent, re-evaluates the new factors on every
stored transition and refits the decomposition head on the stored episodes.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from mira.agents.networks import AdamStepper, make_adam
from mira.errors import NonFiniteError
from mira.replay import Batch
from mira.rewards.base import RewardContext
from mira.rewards.episodes import EpisodeStore
from mira.rewards.lookahead import LookaheadSource, Relabelled, resolve
from mira.shaping.beside import Beside
from mira.shaping.columns import FactorColumns
from mira.shaping.config import HarsConfig
from mira.shaping.decomposition import DecompositionHead
from mira.shaping.decomposition import log_fields as head_log_fields
from mira.shaping.factors import (
    META_DIM,
    FactorMeta,
    FactorSource,
    ProgramFactorSource,
    RunningStats,
    meta_features,
)
from mira.shaping.networks import FactorAttentionBlock, FrozenPotential, TemporalContextEncoder, ValuePotential
from mira.shaping.objective import hars_objective

STD_FLOOR = 1e-4
BASE_LOG_FIELDS = ("phi_mean", "phi_std", "l_align", "l_aux", "attn_entropy", "rpe")


def _log_fields(config: HarsConfig, factors: FactorSource) -> tuple[str, ...]:
    head = head_log_fields(list(factors.phi_names), list(factors.aux_names), config.decompose_phi_at)
    return (*BASE_LOG_FIELDS, *(f"attn_{n}" for n in factors.phi_names), *head)


@dataclass
class _Pending:
    """The forward pass made in ``relabel``, reused by ``update`` for the same batch."""

    batch: Batch
    base: torch.Tensor  # [B] the reward Φ is aligned to: r̂ (decomposed) or r_ext (episodic)
    phi: torch.Tensor  # [2B] Φ over [s; s′], with graph
    v: torch.Tensor  # [2B, d_z]
    alpha: torch.Tensor  # [2B, K]
    leaf: torch.Tensor | None  # detached copy of phi the agent backpropagated into (joint mode)
    v_ctx: torch.Tensor | None  # [n, W-1, d_z] TCE context aggregations, with graph
    ctx_valid: torch.Tensor | None  # [n, W-1] bool


@dataclass
class _InputSnapshot:
    """What Φ reads besides its weights, frozen at the first use after each weight change: the input
    normalisation statistics (floored standard deviations) and σ_R, the unit Φ is learned in."""

    f_mean: np.ndarray
    f_std: np.ndarray
    o_mean: np.ndarray
    o_std: np.ndarray
    unit: float


def _has_spare_core() -> bool:
    """Whether this process may run on more cores than PyTorch's intra-op threads use."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return cores > torch.get_num_threads()


def _name_seed(*parts: object) -> int:
    digest = hashlib.sha256(":".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


@contextmanager
def _seeded(seed: int) -> Iterator[None]:
    """Run with torch's CPU generator seeded to ``seed``, leaving the global stream untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


@torch.no_grad()
def _pbrs_rewards(potential: FrozenPotential, f: torch.Tensor, obs: torch.Tensor, reward: torch.Tensor,
                  alive: torch.Tensor, gamma: float, kappa: float, sizes: list[int]) -> list[torch.Tensor]:
    """``r + κ(γ (1 − terminated) Φ(s′) − Φ(s))`` for batches laid end to end (``reward`` and ``alive =
    1 − terminated`` concatenated, ``f`` and ``obs`` with all the s first, then all the s′), from one
    pass of ``potential``; split back into the batches' ``sizes``. A handful of ops whatever the
    number of batches: on the training thread, each op is one more hand-over of the interpreter."""
    phi = potential(f, obs)
    n = reward.shape[0]
    if kappa != 1.0:
        phi = phi * kappa
    return list((reward - phi[:n]).addcmul_(alive, phi[n:], value=gamma).split(sizes))


class HarsReward(LookaheadSource):
    """Hierarchical Attention-based Reward Shaping: decomposition head r̂, FAB → VPM potential Φ aligned
    to r̂, TCE auxiliary; the agent learns from r̂ + κ(γΦ(s′) − Φ(s))."""

    name = "hars"
    log_fields: tuple[str, ...] = BASE_LOG_FIELDS

    def __init__(self, factors: FactorSource, config: HarsConfig | None = None) -> None:
        self.config = config or HarsConfig()
        background = self.config.train_in_background
        self.background = _has_spare_core() if background is None else bool(background)
        """Whether training steps and shaping passes run on the training thread (see HarsConfig)."""
        self.factors: FactorSource = factors
        self.slots: dict[str, int] = {}
        self._assign_slots(factors.phi_names)
        self.log_fields = _log_fields(self.config, factors)
        self.kappa = self.config.kappa()
        """κ, the PBRS term's weight in the agent's reward (see HarsConfig.shaping_weight)."""
        if self.config.alignment not in ("decomposed", "episodic"):
            raise ValueError(f"hars.alignment must be 'decomposed' or 'episodic', not {self.config.alignment!r}")
        self.generation = 0
        self.updates = 0
        self.calls = 0  # agent updates seen; HARS trains on every ``update_every``-th
        self._last_metrics: dict[str, torch.Tensor] | None = None
        self.return_sq: float | None = None  # EMA of squared episodic returns (σ_R², see HarsConfig)
        self._pending: _Pending | None = None
        self._bound = False
        self._last_l_aux = torch.zeros(())
        # Φ's input statistics as of its latest weights (see ``_norm``) and the no-grad potential built
        # from those weights; both are dropped whenever the weights change.
        self._snapshot: _InputSnapshot | None = None
        self._norm_cache: tuple[torch.Tensor, ...] | None = None
        self._frozen: FrozenPotential | None = None
        self._revision = 0  # counts changes of Φ (see ``revision``)
        # The latest training step until it lands (see ``update``), and where it runs.
        self._steps: Beside[tuple[dict[str, torch.Tensor], torch.Tensor]] = Beside(self.background)

    # --------------------------------------------------------------------------------- set-up
    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        cfg = self.config
        self.gamma = float(ctx.gamma)
        self.device = ctx.device
        self.obs_dim = int(ctx.obs_dim)
        self.obs_stats = RunningStats(self.obs_dim)
        self.episodes = EpisodeStore(ctx.buffer, cfg.decompose_max_episodes)
        self._last_l_aux = torch.zeros((), device=self.device)
        with _seeded(_name_seed(ctx.seed, "tce")):
            self.tce = TemporalContextEncoder(cfg.d_z, hidden=cfg.tce_hidden).to(self.device)
        self._install(self.factors)
        self._build_phi_nets(keep_tce_state=False)
        self._bound = True

    def _assign_slots(self, names: Sequence[str]) -> None:
        for n in names:
            if n not in self.slots:
                self.slots[n] = len(self.slots)

    def _install(self, factors: FactorSource) -> None:
        """Point the source at ``factors``: names, slots, columns, static metadata (no networks)."""
        self.factors = factors
        self.phi_names = list(factors.phi_names)
        self.aux_names = list(factors.aux_names)
        self._assign_slots(self.phi_names)
        self._attn_keys = [f"attn_{n}" for n in self.phi_names]
        k = len(self.phi_names)
        self.columns = FactorColumns(factors, self.ctx.buffer, self.obs_stats)
        self._meta_static = meta_features(self.phi_names, factors.meta, np.zeros(k), np.zeros(k))[:, :6]
        self._slot_t = torch.tensor([self.slots[n] for n in self.phi_names], dtype=torch.long, device=self.device)
        self.head = DecompositionHead(self.config, self.phi_names, self.aux_names)
        self._head_changed()

    def _build_phi_nets(self, keep_tce_state: bool) -> None:
        """Fresh FAB (ϕ) and VPM (φ) and a fresh optimiser (keeping ψ's Adam state if asked)."""
        cfg = self.config
        slots = cfg.id_slots
        while slots < len(self.slots):
            slots *= 2
        with _seeded(_name_seed(self.ctx.seed, "phi", self.generation)):
            fab = FactorAttentionBlock(self.obs_dim, d_z=cfg.d_z, id_dim=cfg.id_dim, id_slots=slots,
                                       hidden=cfg.fab_hidden, query_hidden=cfg.query_hidden)
            vpm = ValuePotential(cfg.d_z, self.obs_dim, hidden=cfg.vpm_hidden, state_proj=cfg.vpm_state_proj,
                                 state_proj_dim=cfg.state_proj_dim)
        with torch.no_grad():
            # Each name's initial ID embedding depends on the name (and seed, generation) only, not on
            # its slot, so a fresh FAB gives the same Φ whatever the order the factors are listed in.
            for name, slot in self.slots.items():
                gen = torch.Generator().manual_seed(_name_seed(self.ctx.seed, "id", self.generation, name))
                fab.id_table[slot] = torch.randn(cfg.id_dim, generator=gen)
        self.fab, self.vpm = fab.to(self.device), vpm.to(self.device)
        old = getattr(self, "opt", None)
        params = [*self.fab.parameters(), *self.vpm.parameters(), *self.tce.parameters()]
        self.opt = make_adam(params, cfg.lr)
        self._stepper = AdamStepper(self.opt)  # the same fused Adam step without Optimizer.step's Python
        if keep_tce_state and old is not None:
            for p in self.tce.parameters():
                if p in old.state:
                    self.opt.state[p] = old.state[p]
        self._pending = None
        self.weights_changed()

    def weights_changed(self) -> None:
        """Forget what was derived from the previous weights: the input-statistics snapshot and the
        no-grad potential. The next use takes both afresh."""
        self._snapshot = None
        self._norm_cache = None
        self._frozen = None
        self._revision += 1

    @property
    def revision(self) -> int:
        """Bumped whenever the agent's reward changes: Φ's weights (a training step, a new program, loaded
        state) or the decomposition head's fit (after each episode)."""
        return self._revision

    # ------------------------------------------------------------------------- factor columns
    @property
    def phi_scale(self) -> float:
        """σ_R: the unit Φ is learned in (1 until an episode has ended, or with ``return_scale`` off)."""
        if not self.config.return_scale or self.return_sq is None:
            return 1.0
        return max(1.0, math.sqrt(self.return_sq))

    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> None:
        if not math.isfinite(episode_return):
            return
        sq = float(episode_return) ** 2
        rho = self.config.return_scale_ema
        self.return_sq = sq if self.return_sq is None else (1.0 - rho) * self.return_sq + rho * sq
        if self.episodes.add(rows, episode_return):
            self.head.add_episode(self._head_inputs(np.asarray(rows, dtype=np.int64)), float(episode_return))
            self._head_changed()

    # ------------------------------------------------------------------ decomposition head
    def _head_inputs(self, rows: np.ndarray) -> np.ndarray:
        """The head's features ``[N, D]`` of stored rows, from the factor columns."""
        return self.head.features(*self.columns.numpy_rows(rows))

    def _head_changed(self) -> None:
        """Take the head's new weights: as tensors for relabelling, as figures for the log."""
        w = self.head.weights
        k, k_aux = len(self.phi_names), len(self.aux_names)
        at = self.config.decompose_phi_at
        n_s = k if at in ("state", "both") else 0
        n_n = k if at in ("next", "both") else 0
        t = torch.from_numpy(w.astype(np.float32))
        self._w_s, self._w_n = t[:n_s], t[n_s:n_s + n_n]
        self._w_aux, self._w_bias = t[n_s + n_n:n_s + n_n + k_aux], float(w[-1])
        self._head_metrics = {name: torch.tensor(v, dtype=torch.float32) for name, v in self.head.figures().items()}
        self._revision += 1

    def _decomposed(self, rows: torch.Tensor) -> torch.Tensor:
        """r̂ of stored rows ``[B]`` (their factors must be evaluated), on the source's device."""
        r = torch.full((rows.shape[0],), self._w_bias, dtype=torch.float32)
        if self._w_n.numel():
            r = r.addmv_(self.columns.phi_next.index_select(0, rows), self._w_n)
        if self._w_s.numel():
            r = r.addmv_(self.columns.phi.index_select(0, rows), self._w_s)
        if self._w_aux.numel():
            r = r.addmv_(self.columns.aux.index_select(0, rows), self._w_aux)
        return r.to(self.device)

    def _base_reward(self, batch: Batch, rows: torch.Tensor) -> torch.Tensor:
        """What Φ is aligned to and the agent's reward is built on: r̂, or r_ext (episodic alignment)."""
        if self.config.alignment == "episodic":
            return batch.reward
        return self._decomposed(rows).to(batch.reward.device)

    def decomposed_reward(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray) -> np.ndarray:
        """r̂ of arbitrary transitions (raw arrays, e.g. a held-out rollout's): ``[N]`` float64."""
        o, o2 = self._as_numpy(obs), self._as_numpy(next_obs)
        if o.shape[0] == 0:
            return np.zeros(0)
        aux = self.factors.aux(o, np.asarray(actions, dtype=np.float32)) if self.aux_names else np.zeros((len(o), 0))
        x = self.head.features(self.factors.phi(o), self.factors.phi(o2), aux)
        return np.asarray(x @ self.head.weights, dtype=np.float64)

    def _refit_head(self) -> None:
        """A fresh head for the current program, fitted on every stored episode still intact."""
        self.head = DecompositionHead(self.config, self.phi_names, self.aux_names)
        self.episodes.prune()
        start, cap = self.episodes.intact_start(), self.ctx.buffer.capacity
        for i in range(start, len(self.episodes)):
            first, n = int(self.episodes.first[i]), int(self.episodes.length[i])
            rows = (first + np.arange(n)) % cap
            self.head.add_episode(self._head_inputs(rows), float(self.episodes.returns[i]))
        self._head_changed()

    def on_transition(self, row: int) -> None:
        self.columns.add(row)

    @property
    def factor_stats(self) -> RunningStats:
        """Running statistics of the current program's PHI values (Φ normalises its inputs with them)."""
        return self.columns.factor_stats

    def flush_factors(self) -> None:
        """Evaluate the factors of every stored row not evaluated yet (see :mod:`mira.shaping.columns`)."""
        self.columns.flush()

    def recompute_all(self, reset_stats: bool = True) -> None:
        """Re-evaluate every stored transition's factors (after a program change); with ``reset_stats``
        the factor normalisation statistics restart from the stored states."""
        self.columns.recompute_all(self.config.recompute_chunk, reset_stats)

    # ------------------------------------------------------------------------------- forward
    def _norm(self) -> tuple[torch.Tensor, ...]:
        """Normalisation tensors of factors and observations and the metadata matrix, on the device.

        The running statistics (and σ_R) move with every stored transition, but Φ reads a snapshot
        of them taken at the first use after each change of Φ's weights: they are part of the
        potential, so Φ is one fixed function between two HARS training steps (the shaping of every
        batch in between evaluates that same function, and its derived tensors are built once). The
        snapshot is checkpointed so a resumed run uses the same one.
        """
        if self._norm_cache is None:
            if self._snapshot is None:
                self.flush_factors()
                self._snapshot = _InputSnapshot(
                    self.factor_stats.mean.copy(), np.maximum(self.factor_stats.std, STD_FLOOR),
                    self.obs_stats.mean.copy(), np.maximum(self.obs_stats.std, STD_FLOOR), self.phi_scale)
            snap = self._snapshot
            f_mean, f_std, o_mean, o_std = snap.f_mean, snap.f_std, snap.o_mean, snap.o_std
            meta = np.concatenate([self._meta_static, np.stack([np.sign(f_mean) * np.log1p(np.abs(f_mean)),
                                                                np.log1p(f_std)], axis=1)], axis=1)
            self._norm_cache = (*self._affine(f_mean, f_std), self._tensor(meta), *self._affine(o_mean, o_std))
        return self._norm_cache

    def _tensor(self, a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.asarray(a, dtype=np.float32)).to(self.device)

    def _affine(self, mean: np.ndarray, std: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """``(shift, inv)`` with ``x · inv + shift = (x − mean) / std``: normalisation as one fused
        multiply-add (computed in float64, stored in float32)."""
        return self._tensor(-mean / std), self._tensor(1.0 / std)

    def _unit(self) -> float:
        """σ_R as of the current weights (the snapshot's, see ``_norm``)."""
        self._norm()
        assert self._snapshot is not None
        return self._snapshot.unit

    def _normalise(self, f: torch.Tensor, obs: torch.Tensor, norm: tuple[torch.Tensor, ...]
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised, clipped factor values ``x`` and observations ``o``: the networks' inputs."""
        f_shift, f_inv, _, o_shift, o_inv = norm
        c = self.config.input_clip
        return torch.addcmul(f_shift, f, f_inv).clamp_(-c, c), torch.addcmul(o_shift, obs, o_inv).clamp_(-c, c)

    def _ensure_frozen(self) -> FrozenPotential:
        if self._frozen is None:
            f_shift, f_inv, meta, o_shift, o_inv = self._norm()
            self._frozen = FrozenPotential(self.fab, self.vpm, self.fab.ids(self._slot_t).detach(), meta,
                                           f_shift=f_shift, f_inv=f_inv, o_shift=o_shift, o_inv=o_inv,
                                           clip=self.config.input_clip, unit=self._unit())
        return self._frozen

    def _potential_no_grad(self, f: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """Φ of every row, without a graph (the shaping of a batch HARS does not train on)."""
        return self._ensure_frozen()(f, obs)

    def _forward(self, f: torch.Tensor, obs: torch.Tensor, norm: tuple[torch.Tensor, ...],
                 ids: torch.Tensor | None = None, n_phi: int | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Φ ``[n_phi]``, v ``[N, d_z]`` and α ``[N, K]`` from raw factor values and raw observations
        (Φ only for the first ``n_phi`` rows, default all)."""
        x, o = self._normalise(f, obs, norm)
        v, alpha = self.fab(x, o, self.fab.ids(self._slot_t) if ids is None else ids, norm[2])
        scale = self._unit()
        if n_phi is None:
            return self.vpm(v, o) * scale, v, alpha
        return self.vpm(v[:n_phi], o[:n_phi]) * scale, v, alpha

    def _window_rows(self, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Buffer rows of the W − 1 steps before each of ``rows`` (oldest first) and their validity."""
        buf = self.ctx.buffer
        w = self.config.tce_window
        r = torch.from_numpy(rows)
        offs = torch.arange(w - 1, 0, -1)
        past = (r[:, None] - offs[None, :]) % buf.capacity
        valid = (buf.episode_step[r][:, None] >= offs[None, :]) & (buf.episode_id[past] == buf.episode_id[r][:, None])
        return past, valid

    def relabel(self, batch: Batch) -> torch.Tensor:
        b = batch.reward.shape[0]
        cfg = self.config
        if not (torch.is_grad_enabled() and self._trains_now()):
            return resolve(self._shape_frozen([batch])[0])
        self.sync()  # this batch is shaped, with a graph, by the latest weights
        with_tce = cfg.aux_weight > 0 and cfg.tce_window >= 2 and self.updates % max(1, cfg.tce_every) == 0
        if with_tce:
            self.columns.flush()  # the windows read rows before the batch's
        else:
            self.columns.ensure(batch.indices)
        idx = torch.from_numpy(batch.indices)
        f = torch.cat([self.columns.phi.index_select(0, idx), self.columns.phi_next.index_select(0, idx)])
        obs = torch.cat([batch.obs, batch.next_obs])
        n_ctx = 0
        past = valid = None
        if with_tce:
            n_ctx = b if cfg.tce_batch is None else min(b, cfg.tce_batch)
            past, valid = self._window_rows(batch.indices[:n_ctx])
            flat = past.reshape(-1)
            f = torch.cat([f.to(self.device), self.columns.phi[flat].to(self.device)])
            obs = torch.cat([obs, self.ctx.buffer.obs[flat].to(self.device)])
        phi, v_all, alpha_all = self._forward(f.to(self.device), obs, self._norm(), n_phi=2 * b)
        v, alpha = v_all[: 2 * b], alpha_all[: 2 * b]
        base = self._base_reward(batch, idx)
        joint = cfg.joint and self.kappa != 0.0
        leaf = phi.detach()
        if joint:
            leaf.requires_grad_(True)
        v_ctx = v_all[2 * b :].reshape(n_ctx, cfg.tce_window - 1, -1) if past is not None else None
        self._pending = _Pending(batch, base, phi, v, alpha, leaf if joint else None, v_ctx,
                                 None if valid is None else valid.to(self.device))
        if self.kappa == 0.0:
            return base
        return base + self.kappa * (self.gamma * (1.0 - batch.terminated) * leaf[b:] - leaf[:b])

    def lookahead(self) -> int:
        # Φ is one fixed function from one training update to the next, so the batches of a whole
        # cycle can be shaped when its training batch is: that one with a graph, the rest in one pass.
        every = max(1, self.config.update_every)
        if self._last_metrics is None:
            return 1  # the first training step lands at once: the next batches are shaped after it
        return every - self.calls % every

    def relabel_many(self, batches: list[Batch]) -> list[Relabelled]:
        """The batches of the updates until the next training step: the first with a graph when it is
        the training batch, the others in one no-grad pass of Φ, which costs much less than a forward
        per batch (fewer dispatches, and the agent's updates in between no longer evict Φ's data each
        time). With ``train_in_background`` that pass runs on the training thread, while the agent
        updates on the first batch, and the rewards after the first are Futures."""
        if not batches:
            return []
        if torch.is_grad_enabled() and self._trains_now():
            first = self.relabel(batches[0])  # lands the step in flight first: the rest see its Φ too
            return [first, *self._shape_frozen(batches[1:], self.background)]
        return list(self._shape_frozen(batches, self.background))

    @torch.no_grad()
    def _shape_frozen(self, batches: list[Batch], background: bool = False) -> list[Relabelled]:
        """Agent rewards ``base + κ(γ (1 − terminated) Φ(s′) − Φ(s))`` of ``batches`` from one no-grad
        pass of the current Φ over all their [s; s′] (absorbing terminals; a truncation keeps Φ(s′)).
        The inputs and the base rewards are gathered here; with ``background`` the pass runs on the
        training thread. With κ = 0 there is no pass: the reward is the base reward."""
        if not batches:
            return []
        idx = np.concatenate([b.indices for b in batches])
        self.columns.ensure(idx)
        rows = torch.from_numpy(idx)
        sizes = [b.reward.shape[0] for b in batches]
        if self.config.alignment == "episodic":
            reward = torch.cat([b.reward for b in batches])
        else:
            reward = self._decomposed(rows).to(batches[0].reward.device)
        if self.kappa == 0.0:
            return list(reward.split(sizes))
        cols = self.columns
        f = torch.cat([cols.phi.index_select(0, rows), cols.phi_next.index_select(0, rows)]).to(self.device)
        obs = torch.cat([*(b.obs for b in batches), *(b.next_obs for b in batches)])
        alive = 1.0 - torch.cat([b.terminated for b in batches])
        args = (self._ensure_frozen(), f, obs, reward, alive, self.gamma, self.kappa, sizes)
        if not background:
            return list(_pbrs_rewards(*args))
        return list(self._steps.split(_pbrs_rewards, len(batches), *args))

    # -------------------------------------------------------------------------------- update
    def _trains_now(self) -> bool:
        # Always train when there are no figures to report yet (start, or a new program's first batch).
        return self._last_metrics is None or self.calls % max(1, self.config.update_every) == 0

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        """Count the agent's update; on every ``update_every``-th, launch a training step of (ϕ, φ, ψ).

        The step lands (its weights start shaping, its figures are reported) at the next training
        update, or earlier when Φ is read (:meth:`sync`); until then the batches are shaped by the
        potential that shaped this one. That is what lets the step run on a second thread
        (``HarsConfig.train_in_background``) beside the agent's next updates, and it is the same
        computation either way. The figures returned are those of the latest step that landed.
        """
        if not self._trains_now():
            assert self._last_metrics is not None
            self.calls += 1
            self._pending = None
            return {**self._last_metrics, **self._head_metrics}  # the latest training step's figures
        pending, self._pending = self._pending, None
        if pending is None or pending.batch is not batch:
            with torch.enable_grad():
                self.relabel(batch)
            pending, self._pending = self._pending, None
            assert pending is not None
            pending.leaf = None  # no critic gradient was taken through this forward
        # Everything the step reads from the source is taken here, on the caller's thread: σ_R, the
        # previous L_aux, and the no-grad potential that keeps shaping the batches until it lands.
        self._ensure_frozen()
        unit, last_l_aux = self._unit(), self._last_l_aux
        self.updates += 1
        self.calls += 1
        first = self._last_metrics is None  # nothing to report yet: this step lands at once
        self._steps.start(self._train_step, pending, batch, unit, last_l_aux, inline=first)
        if first:
            self.sync()
        assert self._last_metrics is not None
        return {**self._last_metrics, **self._head_metrics}

    def sync(self) -> None:
        """Land the training step in flight, if any: wait for it, adopt its figures, and let Φ's new
        weights shape from now on. Every read of Φ (shaping with a graph, ``potential``, monitor
        helpers, checkpoints, program changes) does this first."""
        landed = self._steps.land()
        if landed is None:
            return
        metrics, l_aux = landed
        if not bool(torch.isfinite(torch.stack(list(metrics.values()))).all()):
            # Stop before anything (a checkpoint, the next batch) uses the weights this step produced.
            bad = sorted(k for k, v in metrics.items() if not bool(torch.isfinite(v)))
            raise NonFiniteError(f"HARS training step {self.updates} (agent update {self.calls}): non-finite "
                                 f"{', '.join(bad)}; the run stopped and its last checkpoint is intact: lower "
                                 "hars.lr or check the reward program, then --resume")
        self._last_metrics, self._last_l_aux = metrics, l_aux
        self.weights_changed()

    def close(self) -> None:
        self.sync()
        self._steps.close()

    def _train_step(self, pending: _Pending, batch: Batch, unit: float, last_l_aux: torch.Tensor
                    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """One optimiser step of eq. (10) on ``batch`` from the forward made in ``relabel``; returns the
        step's figures and the latest L_aux. Reads only its arguments and (ϕ, φ, ψ) and their
        optimiser, so it may run on another thread while the agent updates."""
        cfg = self.config
        b = batch.reward.shape[0]
        terms = hars_objective(cfg, self.tce, phi=pending.phi, v=pending.v, alpha=pending.alpha, v_ctx=pending.v_ctx,
                               ctx_valid=pending.ctx_valid, reward=pending.base, terminated=batch.terminated,
                               gamma=self.gamma, unit=unit)
        if pending.v_ctx is not None:
            last_l_aux = terms.l_aux.detach()
        loss = terms.loss
        if pending.leaf is not None and pending.leaf.grad is not None:
            # The critic's loss is quadratic in reward units: σ_R² brings it to the alignment loss's units.
            loss = loss + (pending.leaf.grad * pending.phi).sum() / (unit * unit)
        loss.backward()
        if cfg.max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_([p for g in self.opt.param_groups for p in g["params"]],
                                           cfg.max_grad_norm)
        self._stepper.step()
        self._stepper.zero_grad()
        with torch.no_grad():
            phi_d = pending.phi[:b].detach()
            metrics = {
                "phi_mean": phi_d.mean(),
                "phi_std": phi_d.std(unbiased=False),
                "l_align": terms.l_align.detach(),
                "l_aux": last_l_aux,  # the latest computed value (L_aux runs every tce_every)
                "attn_entropy": terms.entropy.detach(),
                "rpe": terms.l_td.detach() * unit * unit / (terms.target.var(unbiased=False) + 1e-8),
            }
            if self._attn_keys:
                metrics.update(zip(self._attn_keys, pending.alpha[:b].detach().mean(0).unbind(), strict=True))
        return metrics, last_l_aux

    # ------------------------------------------------------------------ structural update (4.4.5)
    def set_program(self, factors: FactorSource) -> None:
        """Switch to a new factor set: fresh ϕ, φ (and their Adam state), ψ kept, columns recomputed."""
        if not self._bound:  # before training: nothing to re-initialise yet
            self.factors = factors
            self._assign_slots(factors.phi_names)
            self.log_fields = _log_fields(self.config, factors)
            return
        self.sync()
        self.generation += 1
        self.flush_factors()  # with the old program: its columns are replaced, its rows' states stay in the statistics
        self._install(factors)
        self.recompute_all(reset_stats=True)
        self._refit_head()
        self._build_phi_nets(keep_tce_state=True)
        self._last_metrics = None  # the old program's figures (and attention keys) no longer apply

    # ---------------------------------------------------------------------- monitor helpers
    def _as_numpy(self, obs: np.ndarray | torch.Tensor) -> np.ndarray:
        if isinstance(obs, torch.Tensor):
            obs = obs.detach().cpu().numpy()
        return np.asarray(obs, dtype=np.float32).reshape(-1, self.obs_dim)

    def _chunks(self, n: int) -> Iterator[slice]:
        step = max(1, self.config.recompute_chunk)
        for start in range(0, n, step):
            yield slice(start, min(n, start + step))

    @torch.no_grad()
    def potential(self, obs: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Current Φ(s) of a batch of raw observations ``[B, obs_dim]`` (CPU tensor ``[B]``, no grad)."""
        self.sync()
        o = self._as_numpy(obs)
        out = []
        for sl in self._chunks(o.shape[0]):
            f = torch.from_numpy(self.factors.phi(o[sl]).astype(np.float32)).to(self.device)
            out.append(self._potential_no_grad(f, torch.from_numpy(o[sl]).to(self.device)).cpu())
        return torch.cat(out) if out else torch.zeros(0)

    @torch.no_grad()
    def attention(self, obs: np.ndarray | torch.Tensor) -> dict[str, float]:
        """Mean attention weight α_i per PHI factor name over a batch of raw observations."""
        self.sync()
        o = self._as_numpy(obs)
        if o.shape[0] == 0 or not self.phi_names:
            return dict.fromkeys(self.phi_names, 0.0)
        norm = self._norm()
        total = torch.zeros(len(self.phi_names), dtype=torch.float64)
        for sl in self._chunks(o.shape[0]):
            f = torch.from_numpy(self.factors.phi(o[sl]).astype(np.float32)).to(self.device)
            alpha = self._forward(f, torch.from_numpy(o[sl]).to(self.device), norm)[2]
            total += alpha.double().sum(0).cpu()
        return {n: float(a) for n, a in zip(self.phi_names, (total / o.shape[0]).tolist(), strict=True)}

    @torch.no_grad()
    def proxy_potential(self, candidate: FactorSource, obs: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Φ̃(s): a candidate program's PHI factors through the *frozen* FAB/VPM (section 4.4.4).

        Factors the current program also has keep their ID embedding and normalisation statistics.
        A new name has no trained embedding; it gets the mean ID embedding of the current factors
        (the centroid of what the frozen g_ϕ was trained on, i.e. "a typical factor", favouring none)
        and is normalised by its own mean and std over ``obs``. Metadata comes from the candidate.
        """
        self.sync()
        o = self._as_numpy(obs)
        names = list(candidate.phi_names)
        vals = candidate.phi(o).astype(np.float64) if names else np.zeros((o.shape[0], 0))
        pos = {n: j for j, n in enumerate(self.phi_names)}
        _, _, _, o_shift, o_inv = self._norm()  # known factors keep the statistics Φ reads now
        assert self._snapshot is not None
        cur_mean, cur_std = self._snapshot.f_mean, self._snapshot.f_std
        mean = np.array([cur_mean[pos[n]] if n in pos else vals[:, j].mean() if len(vals) else 0.0
                         for j, n in enumerate(names)], dtype=np.float64)
        std = np.array([cur_std[pos[n]] if n in pos else max(float(vals[:, j].std()) if len(vals) else 1.0,
                                                                  STD_FLOOR)
                        for j, n in enumerate(names)], dtype=np.float64)
        meta = meta_features(names, candidate.meta, mean, std)
        known = self.fab.ids(self._slot_t)
        fallback = known.mean(0) if known.shape[0] else torch.zeros(self.config.id_dim, device=self.device)
        ids = torch.stack([known[pos[n]] if n in pos else fallback for n in names]) if names else known[:0]
        norm = (*self._affine(mean, std), self._tensor(meta), o_shift, o_inv)
        out = []
        for sl in self._chunks(o.shape[0]):
            f = torch.from_numpy(vals[sl].astype(np.float32)).to(self.device)
            out.append(self._forward(f, torch.from_numpy(o[sl]).to(self.device), norm, ids=ids)[0].cpu())
        return torch.cat(out) if out else torch.zeros(0)

    # ------------------------------------------------------------------------- bookkeeping
    @property
    def program(self) -> Any:
        """The current :class:`FactorProgram` when the factor source has one (else None)."""
        return getattr(self.factors, "program", None)

    def phi_parameters(self) -> list[torch.nn.Parameter]:
        """ϕ and φ: what a structural edit re-initialises."""
        self.sync()
        return [*self.fab.parameters(), *self.vpm.parameters()]

    def describe(self) -> dict[str, Any]:
        prog = self.program
        return {"method": self.name, "phi_factors": list(self.factors.phi_names),
                "aux_factors": list(self.factors.aux_names), "hars": asdict(self.config),
                "train_in_background": self.background, "alignment": self.config.alignment,
                "kappa": self.kappa,
                "decomposition": self.head.describe() if self._bound else None,
                "program_version": None if prog is None else prog.version}

    def state_dict(self) -> dict[str, Any]:
        self.sync()  # a checkpoint holds the weights with the step taken so far landed
        columns = self.columns.state_dict()  # evaluates pending rows first (flush points stay the same on resume)
        prog = self.program
        return {
            "format": 2,
            "episodes": self.episodes.state_dict(),
            "head": self.head.state_dict(),
            "generation": self.generation,
            "updates": self.updates,
            "calls": self.calls,
            "return_sq": self.return_sq,
            "last_metrics": None if self._last_metrics is None else {
                k: v.detach().cpu() for k, v in self._last_metrics.items()},
            "last_l_aux": self._last_l_aux.detach().cpu(),
            "slots": dict(self.slots),
            "phi_names": list(self.phi_names),
            "aux_names": list(self.aux_names),
            "program": None if prog is None else prog.to_json(),
            "fab": self.fab.state_dict(),
            "vpm": self.vpm.state_dict(),
            "tce": self.tce.state_dict(),
            "opt": self.opt.state_dict(),
            "factor_stats": self.factor_stats.state_dict(),
            "obs_stats": self.obs_stats.state_dict(),
            "input_snapshot": None if self._snapshot is None else asdict(self._snapshot),
            "columns": columns,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.sync()
        if state["program"] is not None and (self.program is None
                                             or self.program.to_json() != state["program"]):
            from mira.factors.program import FactorProgram

            self._install(ProgramFactorSource(FactorProgram.from_json(state["program"]), self.ctx.card))
        if list(self.factors.phi_names) != state["phi_names"] or list(self.factors.aux_names) != state["aux_names"]:
            raise ValueError(f"checkpoint HARS factors {state['phi_names']} | {state['aux_names']} do not match "
                             f"the current program {self.factors.phi_names} | {self.factors.aux_names}")
        self.slots = dict(state["slots"])
        self.generation = int(state["generation"])
        self._install(self.factors)
        self._build_phi_nets(keep_tce_state=False)
        if self.fab.id_slots != state["fab"]["id_table"].shape[0]:
            raise ValueError("checkpoint HARS ID table size does not match")
        self.fab.load_state_dict(state["fab"])
        self.vpm.load_state_dict(state["vpm"])
        self.tce.load_state_dict(state["tce"])
        self.opt.load_state_dict(state["opt"])
        self.updates = int(state["updates"])
        self.calls = int(state.get("calls", self.updates))
        self.return_sq = state.get("return_sq")
        last = state.get("last_metrics")
        self._last_metrics = None if last is None else {k: v.to(self.device) for k, v in last.items()}
        self._last_l_aux = state["last_l_aux"].to(self.device)
        self.factor_stats.load_state_dict(state["factor_stats"])
        self.obs_stats.load_state_dict(state["obs_stats"])
        self.weights_changed()
        snap = state.get("input_snapshot")
        self._snapshot = None if snap is None else _InputSnapshot(**snap)
        self.columns.load_state_dict(state["columns"])
        if "head" in state:  # format 1 (before the decomposition head): the head starts empty
            self.episodes.load_state_dict(state["episodes"])
            self.head.load_state_dict(state["head"])
            self._head_changed()
        self._pending = None


__all__ = ["META_DIM", "FactorMeta", "FactorSource", "HarsReward"]
