"""HARS as a reward source: the decomposed reward r̂ and a learned potential Φ over the program's factors.

What the agent learns from, for a sampled transition (s, a, s′):

    r = r̂(s, a, s′) + κ · (γ · Φ(s′) · (1 − terminated) − Φ(s)) + γ · Ψ(s′) · (1 − terminated) − Ψ(s),

with r̂ the decomposition head's per-step reward (:mod:`mira.shaping.decomposition`, fitted to
episodic returns only) and Φ the FAB → VPM potential TD-aligned to r̂ (:mod:`mira.shaping.objective`).
κ = 0 by default: the agent learns from r̂ alone, and Φ (still aligned to r̂) is what MCM and SRR
read; κ = 1 adds the PBRS term. Under ``hars.alignment=episodic`` (the paper's letter)
r̂ is replaced by the episodic r_ext in both places. Terminals are absorbing; a time-limit truncation
keeps Φ(s′), as the critic keeps bootstrapping.

Ψ is the sum of the program's SHAPE factors, taken as they are written: a fixed potential, not a learned
one and not fitted to the returns (the head never sees them, so r̂ and its weights are the same with or
without them). Why the factor itself rather than a learned Φ over it: a learned Φ is fitted to r̂ and so
refits an escape ramp towards what the returns already pay (its weight goes to about 0), and at κ = 1 on
HumanoidStandup a Φ of the returns' scale swamped r̂'s differences between actions (``docs/results.md``,
design measurements); a written potential keeps the size its author gave it, which the reward engineer sets against the
program's per-step scale. By Ng et al.'s invariance, γΨ(s′) − Ψ(s) leaves the optimal policies of r̂
unchanged; it only changes where the agent looks first. The pieces:

* :mod:`mira.shaping.columns`: each stored transition's factor values, evaluated lazily in batches;
* :mod:`mira.shaping.decomposition`: r̂ and its weights, the section-3 evidence MCM/SRR read;
* :mod:`mira.shaping.objective`: λ L_align + μ L_aux − β H(α), on one screen;
* :mod:`mira.shaping.networks`: FAB (ϕ), VPM (φ), TCE (ψ); ``FactorAttentionBlock.reference`` is the
  plain definition, ``forward`` and :class:`FrozenPotential` the fast paths (tests check they agree);
* :mod:`mira.shaping.potential`: those networks, their optimiser step and the inputs Φ reads;
* this module: relabelling, the training schedule, program changes, checkpoints.

Training schedule (speed, not method). Φ changes only when a HARS training step lands: its weights
and the input statistics and σ_R it reads are one fixed function from one training update to the next,
so the trainer hands a whole cycle's batches over together (``lookahead`` / ``relabel_many``) when the
training batch is due: that batch is shaped with a graph, the others by a :class:`FrozenPotential`
built once, in one forward pass. The step taken on a cycle's training batch lands at the next cycle's
training batch (or when Φ is read earlier: the monitor, a checkpoint, a program change; see ``sync``),
which is what lets it run, with the cycle's no-grad shaping pass, on a second thread while the agent
updates (when a core is free for it, see ``HarsReward.background``). Where the step runs changes
nothing in the computation (``tests/test_shaping_e2e.py`` checks bit for bit). r̂ changes only at
episode ends (``revision``).

Joint objective (eq. 10). With κ ≠ 0 the reward handed to the agent carries gradient into (ϕ, φ): the
critic's TD loss L_RL is minimised over the shaping parameters as well. Rather than
letting the agent's ``backward`` walk the HARS graph, the reward is built from a detached leaf copy of
Φ; the agent's backward deposits ∂L_RL/∂Φ on that leaf, and the training step backpropagates
``objective + ⟨∂L_RL/∂Φ, Φ⟩`` through the HARS graph once: by the chain rule exactly the gradient of
``L_RL + objective`` w.r.t. (ϕ, φ, ψ). The decomposition head is never trained by either loss.

A structural edit (``set_program``, section 4.4.5) re-initialises ϕ and φ and their optimiser state,
keeps ψ (and its optimiser state) and never touches the agent, re-evaluates the new factors on every
stored transition and refits the decomposition head on the stored episodes.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from mira.errors import NonFiniteError
from mira.factors.program import FactorProgram
from mira.replay import Batch
from mira.rewards.base import RewardContext
from mira.rewards.lookahead import LookaheadSource, Relabelled, resolve
from mira.shaping.beside import Beside
from mira.shaping.columns import FactorColumns, window_rows
from mira.shaping.config import HarsConfig
from mira.shaping.decomposition import DecompositionHead
from mira.shaping.decomposition import log_fields as head_log_fields
from mira.shaping.factors import META_DIM, FactorMeta, FactorSource, ProgramFactorSource
from mira.shaping.memory import FactorMemory
from mira.shaping.networks import FrozenPotential
from mira.shaping.potential import Pending, PotentialNetworks

BASE_LOG_FIELDS = ("phi_mean", "phi_std", "l_align", "l_aux", "attn_entropy", "rpe")
TCE_WINDOW = 8
"""Consecutive same-episode steps a TCE window spans (the last one is the target): a short history,
enough to predict the next aggregation."""
TCE_BATCH = 32
"""Sampled rows whose windows feed L_aux when it is computed: a sample of the batch keeps the GRU's
chain of small sequential ops cheap."""
TCE_EVERY = 4
"""Compute L_aux (and step ψ) on every this many HARS training steps: the auxiliary signal at a fraction
of its cost (Algorithm 3 computes it on every step)."""


def _log_fields(factors: FactorSource) -> tuple[str, ...]:
    head = head_log_fields(list(factors.phi_names), list(factors.aux_names))
    return (*BASE_LOG_FIELDS, *(f"attn_{n}" for n in factors.phi_names), *head)


def _has_spare_core() -> bool:
    """Whether a core is free for a second thread: this process may run on more cores than PyTorch's
    intra-op threads use, and the machine's load (other runs included) leaves one idle."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    try:
        busy = os.getloadavg()[0]
    except OSError:  # no load average on this platform: judge by the affinity alone
        busy = 0.0
    # Half a core of slack: the load average lags, and this process has barely started.
    return cores > torch.get_num_threads() and cores - busy - torch.get_num_threads() >= 0.5


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


def _check_finite(metrics: dict[str, torch.Tensor], what: str) -> None:
    if not bool(torch.isfinite(torch.stack(list(metrics.values()))).all()):
        bad = sorted(k for k, v in metrics.items() if not bool(torch.isfinite(v)))
        raise NonFiniteError(f"{what}: non-finite {', '.join(bad)}; the run stopped and its last checkpoint is "
                             "intact: lower hars.lr or check the reward program, then --resume")


def _network_inputs(columns: FactorColumns, batch: Batch, n_ctx: int, window: int, device: torch.device
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Raw PHI values and observations at [s; s′] of a batch, then (with ``n_ctx`` > 0) at the W − 1 steps
    before each of its first ``n_ctx`` rows (the TCE's windows), and those windows' validity."""
    idx = torch.from_numpy(batch.indices)
    f = torch.cat([columns.phi.index_select(0, idx), columns.phi_next.index_select(0, idx)])
    obs = torch.cat([batch.obs, batch.next_obs])
    if n_ctx == 0:
        return f, obs, None
    past, valid = window_rows(columns.buffer, batch.indices[:n_ctx], window)
    flat = past.reshape(-1)
    f = torch.cat([f.to(device), columns.phi[flat].to(device)])
    obs = torch.cat([obs, columns.buffer.obs[flat].to(device)])
    return f, obs, valid


def _forward_with_graph(nets: PotentialNetworks, columns: FactorColumns, batch: Batch, base: torch.Tensor,
                        n_ctx: int, joint: bool) -> Pending:
    """The forward a training batch is shaped with: Φ at [s; s′] with its graph (and, with ``n_ctx`` > 0,
    the TCE windows' aggregations), kept for the training step. With ``joint`` the agent's reward is
    built on a detached leaf copy of Φ, where the critic's backward leaves ∂L_RL/∂Φ (module docstring)."""
    b, window, device = batch.reward.shape[0], TCE_WINDOW, nets.device
    f, obs, valid = _network_inputs(columns, batch, n_ctx, window, device)
    phi, v_all, alpha_all = nets.forward(f.to(device), obs, nets.norm(), n_phi=2 * b)
    leaf = phi.detach().requires_grad_(True) if joint else None
    v_ctx = v_all[2 * b :].reshape(n_ctx, window - 1, -1) if valid is not None else None
    return Pending(batch, base, phi, v_all[: 2 * b], alpha_all[: 2 * b], leaf, v_ctx,
                   None if valid is None else valid.to(device))


def _shaping_term(columns: FactorColumns, indices: np.ndarray, terminated: torch.Tensor, gamma: float) -> torch.Tensor:
    """γΨ(s′)(1 − terminated) − Ψ(s) of stored rows, Ψ the sum of the program's SHAPE factors (absorbing
    terminals; a truncation keeps Ψ(s′))."""
    columns.ensure(indices)
    rows = torch.from_numpy(indices)
    psi, psi_next = columns.psi.index_select(0, rows), columns.psi_next.index_select(0, rows)
    return (gamma * (1.0 - terminated.to(psi.device)) * psi_next - psi).to(terminated.device)


def _as_numpy(obs: np.ndarray | torch.Tensor, obs_dim: int) -> np.ndarray:
    if isinstance(obs, torch.Tensor):
        obs = obs.detach().cpu().numpy()
    return np.asarray(obs, dtype=np.float32).reshape(-1, obs_dim)


class HarsReward(LookaheadSource):
    """Hierarchical Attention-based Reward Shaping: decomposition head r̂, FAB → VPM potential Φ aligned
    to r̂, TCE auxiliary; the agent learns from r̂ + κ(γΦ(s′) − Φ(s))."""

    name = "hars"
    log_fields: tuple[str, ...] = BASE_LOG_FIELDS

    def __init__(self, factors: FactorSource, config: HarsConfig | None = None, *,
                 background: bool | None = None) -> None:
        self.config = config or HarsConfig()
        self.background = _has_spare_core() if background is None else bool(background)
        """Whether each training step of (ϕ, φ, ψ) and each cycle's no-grad shaping pass run on a second
        (training) thread beside the agent's updates. The step lands at the next training update either
        way, so the run is the same computation, bit for bit, whatever this is. ``background`` None
        (what a run uses): on when a core is free for it (see :func:`_has_spare_core`; otherwise the
        thread would wait for a core, or take one from another run); False: all on the caller's thread."""
        self.factors: FactorSource = factors
        self.nets = PotentialNetworks(self.config)
        self.nets.assign_slots(factors.phi_names)
        self.log_fields = _log_fields(factors)
        self.kappa = self.config.kappa()
        """κ, the PBRS term's weight in the agent's reward (see HarsConfig.shaping_weight)."""
        if self.config.alignment not in ("decomposed", "episodic"):
            raise ValueError(f"hars.alignment must be 'decomposed' or 'episodic', not {self.config.alignment!r}")
        self.updates, self.calls = 0, 0  # training steps taken; agent updates seen (see ``update_every``)
        self._last_metrics: dict[str, torch.Tensor] | None = None
        self._pending: Pending | None = None
        self._bound = False
        self._last_l_aux = torch.zeros(())
        self._revision = 0  # counts changes of the agent's reward (see ``revision``)
        # The latest training step until it lands (see ``update``), and where it runs.
        self._steps: Beside[tuple[dict[str, torch.Tensor], torch.Tensor]] = Beside(self.background)

    # --------------------------------------------------------------------------------- set-up
    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        self.gamma = float(ctx.gamma)
        self.device = ctx.device
        self.obs_dim = int(ctx.obs_dim)
        self.memory = FactorMemory(ctx.buffer, self.obs_dim)
        self._last_l_aux = torch.zeros((), device=self.device)
        self.nets.bind(self.obs_dim, self.device, ctx.seed, self.memory.input_snapshot)
        self._install(self.factors)
        self._build_phi_nets(keep_tce_state=False)
        self._bound = True

    def _install(self, factors: FactorSource, recompute: bool = False) -> None:
        """Point the source at ``factors``: names, columns and r̂ (recomputed from the stored transitions
        with ``recompute``), the networks' inputs."""
        self.factors, self.log_fields = factors, _log_fields(factors)
        self.phi_names, self.aux_names = list(factors.phi_names), list(factors.aux_names)
        self.memory.install(factors, recompute)
        self.columns, self.decomposed = self.memory.columns, self.memory.decomposed
        self.nets.install(self.phi_names, factors.meta)
        self._revision += 1

    def _build_phi_nets(self, keep_tce_state: bool) -> None:
        self.nets.build(keep_tce_state)
        self._pending = None
        self._revision += 1

    def weights_changed(self) -> None:
        """Φ's weights were changed from outside ``update``: forget what was derived from the old ones."""
        self.nets.weights_changed()
        self._revision += 1

    @property
    def revision(self) -> int:
        """Bumped whenever the agent's reward changes: Φ's weights (a training step, a new program, loaded
        state) or the decomposition head's fit (after each episode)."""
        return self._revision

    @property
    def head(self) -> DecompositionHead:
        """The decomposition head of the current program (its weights, shares and fit)."""
        return self.decomposed.head

    # ------------------------------------------------------------------- stored transitions
    def on_transition(self, row: int) -> None:
        self.columns.add(row)

    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> None:
        if self.memory.on_episode_end(rows, episode_return):
            self._revision += 1

    def decomposed_reward(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray) -> np.ndarray:
        """r̂ of arbitrary transitions (raw arrays, e.g. a held-out rollout's): ``[N]`` float64."""
        o, o2 = _as_numpy(obs, self.obs_dim), _as_numpy(next_obs, self.obs_dim)
        return self.decomposed.of_transitions(o, actions, o2)

    # ---------------------------------------------------------------------------- relabelling
    def relabel(self, batch: Batch) -> torch.Tensor:
        b, cfg = batch.reward.shape[0], self.config
        if not (torch.is_grad_enabled() and self._trains_now()):
            return resolve(self._shape_frozen([batch])[0])
        self.sync()  # this batch is shaped, with a graph, by the latest weights
        with_tce = self.updates % TCE_EVERY == 0
        if with_tce:
            self.columns.flush()  # the windows read rows before the batch's
        else:
            self.columns.ensure(batch.indices)
        n_ctx = min(b, TCE_BATCH) if with_tce else 0
        # What Φ is aligned to and the agent's reward is built on: r̂, or r_ext (episodic alignment).
        base = batch.reward if cfg.alignment == "episodic" else \
            self.decomposed.of_rows(torch.from_numpy(batch.indices)).to(batch.reward.device)
        self._pending = _forward_with_graph(self.nets, self.columns, batch, base, n_ctx, joint=self.kappa != 0.0)
        shaped = base
        if self.kappa != 0.0:
            phi = self._pending.leaf if self._pending.leaf is not None else self._pending.phi.detach()
            shaped = base + self.kappa * (self.gamma * (1.0 - batch.terminated) * phi[b:] - phi[:b])
        if self.columns.shaping:  # outside Φ's alignment target: the agent's reward alone carries it
            shaped = shaped + _shaping_term(self.columns, batch.indices, batch.terminated, self.gamma)
        return shaped

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
        time). With ``background`` that pass runs on the training thread, while the agent
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
        reward = torch.cat([b.reward for b in batches]) if self.config.alignment == "episodic" else \
            self.decomposed.of_rows(rows).to(batches[0].reward.device)
        if self.columns.shaping:
            reward = reward + _shaping_term(self.columns, idx, torch.cat([b.terminated for b in batches]), self.gamma)
        if self.kappa == 0.0:
            return list(reward.split(sizes))
        cols = self.columns
        f = torch.cat([cols.phi.index_select(0, rows), cols.phi_next.index_select(0, rows)]).to(self.device)
        obs = torch.cat([*(b.obs for b in batches), *(b.next_obs for b in batches)])
        alive = 1.0 - torch.cat([b.terminated for b in batches])
        args = (self.nets.frozen(), f, obs, reward, alive, self.gamma, self.kappa, sizes)
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
        (``background``) beside the agent's next updates, and it is the same
        computation either way. The figures returned are those of the latest step that landed.
        """
        if not self._trains_now():
            assert self._last_metrics is not None
            self.calls += 1
            self._pending = None
            return {**self._last_metrics, **self.decomposed.metrics}  # the latest training step's figures
        pending, self._pending = self._pending, None
        if pending is None or pending.batch is not batch:
            with torch.enable_grad():
                self.relabel(batch)
            pending, self._pending = self._pending, None
            assert pending is not None
            pending.leaf = None  # no critic gradient was taken through this forward
        # Everything the step reads from the source is taken here, on the caller's thread: σ_R, the
        # previous L_aux, and the no-grad potential that keeps shaping the batches until it lands.
        self.nets.frozen()
        unit, last_l_aux = self.nets.unit(), self._last_l_aux
        self.updates += 1
        self.calls += 1
        first = self._last_metrics is None  # nothing to report yet: this step lands at once
        self._steps.start(self.nets.train_step, pending, self.gamma, unit, last_l_aux, inline=first)
        if first:
            self.sync()
        assert self._last_metrics is not None
        return {**self._last_metrics, **self.decomposed.metrics}

    def sync(self) -> None:
        """Land the training step in flight, if any: wait for it, adopt its figures, and let Φ's new
        weights shape from now on. Every read of Φ (shaping with a graph, ``potential``, monitor
        helpers, checkpoints, program changes) does this first."""
        landed = self._steps.land()
        if landed is None:
            return
        metrics, l_aux = landed
        # Stop before anything (a checkpoint, the next batch) uses the weights this step produced.
        _check_finite(metrics, f"HARS training step {self.updates} (agent update {self.calls})")
        self._last_metrics, self._last_l_aux = metrics, l_aux
        self.weights_changed()

    def close(self) -> None:
        self.sync()
        self._steps.close()

    # ------------------------------------------------------------------ structural update (4.4.5)
    def set_program(self, factors: FactorSource) -> None:
        """Switch to a new factor set: fresh ϕ, φ (and their Adam state), ψ kept, columns recomputed,
        the decomposition head refitted on the stored episodes."""
        if not self._bound:  # before training: nothing to re-initialise yet
            self.factors = factors
            self.nets.assign_slots(factors.phi_names)
            self.log_fields = _log_fields(factors)
            return
        self.sync()
        self.nets.generation += 1
        self._install(factors, recompute=True)
        self._build_phi_nets(keep_tce_state=True)
        self._last_metrics = None  # the old program's figures (and attention keys) no longer apply

    # ---------------------------------------------------------------------- monitor helpers
    def potential(self, obs: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Current Φ(s) of a batch of raw observations ``[B, obs_dim]`` (CPU tensor ``[B]``, no grad)."""
        self.sync()
        return self.nets.potential(self.factors, _as_numpy(obs, self.obs_dim))

    def attention(self, obs: np.ndarray | torch.Tensor) -> dict[str, float]:
        """Mean attention weight α_i per PHI factor name over a batch of raw observations."""
        self.sync()
        return self.nets.attention(self.factors, _as_numpy(obs, self.obs_dim))

    def proxy_potential(self, candidate: FactorSource, obs: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Φ̃(s): a candidate program's PHI factors through the frozen FAB/VPM (section 4.4.4; see
        :meth:`PotentialNetworks.proxy_potential`)."""
        self.sync()
        return self.nets.proxy_potential(candidate, _as_numpy(obs, self.obs_dim))

    # ------------------------------------------------------------------------- bookkeeping
    @property
    def program(self) -> Any:
        """The current :class:`FactorProgram` when the factor source has one (else None)."""
        return getattr(self.factors, "program", None)

    def describe(self) -> dict[str, Any]:
        prog = self.program
        return {"method": self.name, "phi_factors": list(self.factors.phi_names),
                "aux_factors": list(self.factors.aux_names), "hars": asdict(self.config),
                "shape_factors": list(getattr(self.factors, "shape_names", [])), "kappa": self.kappa,
                "train_in_background": self.background, "alignment": self.config.alignment,
                "decomposition": self.head.describe() if self._bound else None,
                "program_version": None if prog is None else prog.version}

    def state_dict(self) -> dict[str, Any]:
        self.sync()  # a checkpoint holds the weights with the step taken so far landed
        prog = self.program
        return {
            "format": 2,
            **self.memory.state_dict(),
            **self.nets.state_dict(),
            "updates": self.updates, "calls": self.calls,
            "last_metrics": None if self._last_metrics is None else {
                k: v.detach().cpu() for k, v in self._last_metrics.items()},
            "last_l_aux": self._last_l_aux.detach().cpu(),
            "phi_names": list(self.phi_names), "aux_names": list(self.aux_names),
            "program": None if prog is None else prog.to_json(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.sync()
        if state["program"] is not None and (self.program is None
                                             or self.program.to_json() != state["program"]):
            self._install(ProgramFactorSource(FactorProgram.from_json(state["program"]), self.ctx.card))
        if list(self.factors.phi_names) != state["phi_names"] or list(self.factors.aux_names) != state["aux_names"]:
            raise ValueError(f"checkpoint HARS factors {state['phi_names']} | {state['aux_names']} do not match "
                             f"the current program {self.factors.phi_names} | {self.factors.aux_names}")
        self.nets.slots = dict(state["slots"])
        self.nets.generation = int(state["generation"])
        self._install(self.factors)
        self._build_phi_nets(keep_tce_state=False)
        self.nets.load_weights(state)
        self._revision += 1
        self.updates, self.calls = int(state["updates"]), int(state.get("calls", state["updates"]))
        last = state.get("last_metrics")
        self._last_metrics = None if last is None else {k: v.to(self.device) for k, v in last.items()}
        self._last_l_aux = state["last_l_aux"].to(self.device)
        self.memory.load_state_dict(state)
        self._pending = None


__all__ = ["META_DIM", "FactorMeta", "FactorSource", "HarsReward"]
