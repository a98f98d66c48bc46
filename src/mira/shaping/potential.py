"""HARS's learned potential Φ: the FAB (ϕ) → VPM (φ) networks over a program's PHI factors, the TCE (ψ)
auxiliary, their optimiser, and the input snapshot Φ reads.

Φ is one fixed function between two training steps: besides its weights it reads the factors' and the
observations' normalisation statistics and σ_R (the unit it is learned in), frozen in an
:class:`InputSnapshot` at the first use after each weight change. Everything derived from the weights
and that snapshot (normalisation tensors, the no-grad :class:`FrozenPotential`) is built once and
dropped by :meth:`PotentialNetworks.weights_changed`. The plain definition of Φ is
``FactorAttentionBlock.reference``; ``forward`` and :class:`FrozenPotential` are the fast paths, which
``tests/test_shaping_networks.py`` checks against it.

This module knows nothing of the replay buffer or of when to train: :class:`mira.shaping.source.HarsReward`
hands it factor values, observations and the forward a training step reads (:class:`Pending`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from mira.agents.networks import AdamStepper, make_adam
from mira.replay import Batch
from mira.shaping.columns import RECOMPUTE_CHUNK
from mira.shaping.config import HarsConfig
from mira.shaping.factors import FactorMeta, FactorSource, meta_features
from mira.shaping.networks import (
    ID_SLOTS,
    FactorAttentionBlock,
    FrozenPotential,
    TemporalContextEncoder,
    ValuePotential,
)
from mira.shaping.objective import hars_objective

STD_FLOOR = 1e-4
INPUT_CLIP = 10.0
"""Normalised factor values and observations are clipped to ±this before entering the networks: a
rare outlier state (a fall, a factor's spike) cannot saturate them."""


@dataclass
class InputSnapshot:
    """What Φ reads besides its weights, frozen at the first use after each weight change: the input
    normalisation statistics (floored standard deviations) and σ_R, the unit Φ is learned in."""

    f_mean: np.ndarray
    f_std: np.ndarray
    o_mean: np.ndarray
    o_std: np.ndarray
    unit: float


@dataclass
class Pending:
    """The forward made when a training batch is shaped, which the training step on it reads."""

    batch: Batch
    base: torch.Tensor  # [B] the reward Φ is aligned to: r̂ (decomposed) or r_ext (episodic)
    phi: torch.Tensor  # [2B] Φ over [s; s′], with graph
    v: torch.Tensor  # [2B, d_z]
    alpha: torch.Tensor  # [2B, K]
    leaf: torch.Tensor | None  # detached copy of phi the agent backpropagated into (joint mode)
    v_ctx: torch.Tensor | None  # [n, W-1, d_z] TCE context aggregations, with graph
    ctx_valid: torch.Tensor | None  # [n, W-1] bool


def name_seed(*parts: object) -> int:
    """A 63-bit seed from names: a network's initial weights depend on what it is, not on call order."""
    digest = hashlib.sha256(":".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


@contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Run with torch's CPU generator seeded to ``seed``, leaving the global stream untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


class PotentialNetworks:
    """ϕ, φ and ψ, their Adam optimiser and the factor-ID slots, for the current program.

    ``inputs`` takes a fresh :class:`InputSnapshot` (the source's running statistics and σ_R). A new
    program (:meth:`install` then :meth:`build`) gets a fresh FAB and VPM and keeps ψ.
    """

    def __init__(self, config: HarsConfig) -> None:
        self.config = config
        self.slots: dict[str, int] = {}
        """Factor name → row of the FAB's ID table; a name keeps its slot across programs."""
        self.generation = 0
        """Programs installed after the first: seeds each program's fresh FAB and VPM."""
        self.snapshot: InputSnapshot | None = None
        self._norm_cache: tuple[torch.Tensor, ...] | None = None
        self._frozen: FrozenPotential | None = None

    def assign_slots(self, names: Sequence[str]) -> None:
        for n in names:
            if n not in self.slots:
                self.slots[n] = len(self.slots)

    def bind(self, obs_dim: int, device: torch.device, seed: int, inputs: Callable[[], InputSnapshot]) -> None:
        """Create ψ (the TCE outlives programs); ϕ and φ come with :meth:`build`."""
        self.obs_dim, self.device, self.seed, self._inputs = obs_dim, device, seed, inputs
        with seeded(name_seed(seed, "tce")):
            self.tce = TemporalContextEncoder().to(device)

    def install(self, phi_names: Sequence[str], meta: Mapping[str, FactorMeta]) -> None:
        """Point the networks' inputs at a program's PHI factors (slots, static metadata)."""
        self.phi_names = list(phi_names)
        self.attn_keys = [f"attn_{n}" for n in self.phi_names]
        self.assign_slots(self.phi_names)
        k = len(self.phi_names)
        self._meta_static = meta_features(self.phi_names, meta, np.zeros(k), np.zeros(k))[:, :6]
        self.slot_t = torch.tensor([self.slots[n] for n in self.phi_names], dtype=torch.long, device=self.device)

    def build(self, keep_tce_state: bool) -> None:
        """Fresh FAB (ϕ) and VPM (φ) and a fresh optimiser (keeping ψ's Adam state if asked)."""
        slots = ID_SLOTS
        while slots < len(self.slots):
            slots *= 2
        with seeded(name_seed(self.seed, "phi", self.generation)):
            fab = FactorAttentionBlock(self.obs_dim, id_slots=slots)
            vpm = ValuePotential()
        with torch.no_grad():
            # Each name's initial ID embedding depends on the name (and seed, generation) only, not on
            # its slot, so a fresh FAB gives the same Φ whatever the order the factors are listed in.
            for name, slot in self.slots.items():
                gen = torch.Generator().manual_seed(name_seed(self.seed, "id", self.generation, name))
                fab.id_table[slot] = torch.randn(fab.id_dim, generator=gen)
        self.fab, self.vpm = fab.to(self.device), vpm.to(self.device)
        old = getattr(self, "opt", None)
        params = [*self.fab.parameters(), *self.vpm.parameters(), *self.tce.parameters()]
        self.opt = make_adam(params, self.config.lr)
        self._stepper = AdamStepper(self.opt)  # the same fused Adam step without Optimizer.step's Python
        if keep_tce_state and old is not None:
            for p in self.tce.parameters():
                if p in old.state:
                    self.opt.state[p] = old.state[p]
        self.weights_changed()

    def weights_changed(self) -> None:
        """Forget what was derived from the previous weights: the input snapshot and the no-grad
        potential. The next use takes both afresh."""
        self.snapshot = None
        self._norm_cache = None
        self._frozen = None

    # ------------------------------------------------------------------------------- forward
    def norm(self) -> tuple[torch.Tensor, ...]:
        """Normalisation tensors of factors and observations and the metadata matrix, on the device,
        from the snapshot (taken now if the weights changed since the last one)."""
        if self._norm_cache is None:
            if self.snapshot is None:
                self.snapshot = self._inputs()
            snap = self.snapshot
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

    def unit(self) -> float:
        """σ_R as of the current weights (the snapshot's)."""
        self.norm()
        assert self.snapshot is not None
        return self.snapshot.unit

    def frozen(self) -> FrozenPotential:
        """Φ without a graph, built once per weight change (the shaping of batches HARS does not train on)."""
        if self._frozen is None:
            f_shift, f_inv, meta, o_shift, o_inv = self.norm()
            self._frozen = FrozenPotential(self.fab, self.vpm, self.fab.ids(self.slot_t).detach(), meta,
                                           f_shift=f_shift, f_inv=f_inv, o_shift=o_shift, o_inv=o_inv,
                                           clip=INPUT_CLIP, unit=self.unit())
        return self._frozen

    def forward(self, f: torch.Tensor, obs: torch.Tensor, norm: tuple[torch.Tensor, ...],
                ids: torch.Tensor | None = None, n_phi: int | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Φ ``[n_phi]``, v ``[N, d_z]`` and α ``[N, K]`` from raw factor values and raw observations
        (Φ only for the first ``n_phi`` rows, default all)."""
        f_shift, f_inv, meta, o_shift, o_inv = norm
        c = INPUT_CLIP
        x = torch.addcmul(f_shift, f, f_inv).clamp_(-c, c)
        o = torch.addcmul(o_shift, obs, o_inv).clamp_(-c, c)
        v, alpha = self.fab(x, o, self.fab.ids(self.slot_t) if ids is None else ids, meta)
        scale = self.unit()
        if n_phi is None:
            return self.vpm(v) * scale, v, alpha
        return self.vpm(v[:n_phi]) * scale, v, alpha

    # -------------------------------------------------------------------------- training step
    def train_step(self, pending: Pending, gamma: float, unit: float, last_l_aux: torch.Tensor
                   ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """One optimiser step of eq. (10) on the pending batch; returns the step's figures and the latest
        L_aux. Reads only its arguments, the networks and their optimiser, so it may run on another
        thread while the agent updates."""
        batch = pending.batch
        b = batch.reward.shape[0]
        terms = hars_objective(self.tce, phi=pending.phi, v=pending.v, alpha=pending.alpha, v_ctx=pending.v_ctx,
                               ctx_valid=pending.ctx_valid, reward=pending.base, terminated=batch.terminated,
                               gamma=gamma, unit=unit)
        if pending.v_ctx is not None:
            last_l_aux = terms.l_aux.detach()
        loss = terms.loss
        if pending.leaf is not None and pending.leaf.grad is not None:
            # The critic's loss is quadratic in reward units: σ_R² brings it to the alignment loss's units.
            loss = loss + (pending.leaf.grad * pending.phi).sum() / (unit * unit)
        loss.backward()
        self._stepper.step()
        self._stepper.zero_grad()
        with torch.no_grad():
            phi_d = pending.phi[:b].detach()
            metrics = {
                "phi_mean": phi_d.mean(),
                "phi_std": phi_d.std(unbiased=False),
                "l_align": terms.l_align.detach(),
                "l_aux": last_l_aux,  # the latest computed value (L_aux runs every TCE_EVERY-th step)
                "attn_entropy": terms.entropy.detach(),
                "rpe": terms.l_td.detach() * unit * unit / (terms.target.var(unbiased=False) + 1e-8),
            }
            if self.attn_keys:
                metrics.update(zip(self.attn_keys, pending.alpha[:b].detach().mean(0).unbind(), strict=True))
        return metrics, last_l_aux

    # ----------------------------------------------------------------- Φ of raw observations
    def _chunks(self, n: int) -> Iterator[slice]:
        step = RECOMPUTE_CHUNK
        for start in range(0, n, step):
            yield slice(start, min(n, start + step))

    @torch.no_grad()
    def potential(self, factors: FactorSource, o: np.ndarray) -> torch.Tensor:
        """Φ(s) of raw observations ``[B, obs_dim]`` (float32) as a CPU tensor ``[B]``."""
        out = []
        for sl in self._chunks(o.shape[0]):
            f = torch.from_numpy(factors.phi(o[sl]).astype(np.float32)).to(self.device)
            out.append(self.frozen()(f, torch.from_numpy(o[sl]).to(self.device)).cpu())
        return torch.cat(out) if out else torch.zeros(0)

    @torch.no_grad()
    def attention(self, factors: FactorSource, o: np.ndarray) -> dict[str, float]:
        """Mean attention weight α_i per PHI factor name over raw observations."""
        if o.shape[0] == 0 or not self.phi_names:
            return dict.fromkeys(self.phi_names, 0.0)
        norm = self.norm()
        total = torch.zeros(len(self.phi_names), dtype=torch.float64)
        for sl in self._chunks(o.shape[0]):
            f = torch.from_numpy(factors.phi(o[sl]).astype(np.float32)).to(self.device)
            alpha = self.forward(f, torch.from_numpy(o[sl]).to(self.device), norm)[2]
            total += alpha.double().sum(0).cpu()
        return {n: float(a) for n, a in zip(self.phi_names, (total / o.shape[0]).tolist(), strict=True)}

    @torch.no_grad()
    def proxy_potential(self, candidate: FactorSource, o: np.ndarray) -> torch.Tensor:
        """Φ̃(s): a candidate program's PHI factors through the *frozen* FAB/VPM (section 4.4.4).

        Factors the current program also has keep their ID embedding and normalisation statistics.
        A new name has no trained embedding; it gets the mean ID embedding of the current factors
        (the centroid of what the frozen g_ϕ was trained on, i.e. "a typical factor", favouring none)
        and is normalised by its own mean and std over ``o``. Metadata comes from the candidate.
        """
        names = list(candidate.phi_names)
        vals = candidate.phi(o).astype(np.float64) if names else np.zeros((o.shape[0], 0))
        pos = {n: j for j, n in enumerate(self.phi_names)}
        _, _, _, o_shift, o_inv = self.norm()  # known factors keep the statistics Φ reads now
        assert self.snapshot is not None
        cur_mean, cur_std = self.snapshot.f_mean, self.snapshot.f_std
        mean = np.array([cur_mean[pos[n]] if n in pos else vals[:, j].mean() if len(vals) else 0.0
                         for j, n in enumerate(names)], dtype=np.float64)
        std = np.array([cur_std[pos[n]] if n in pos else max(float(vals[:, j].std()) if len(vals) else 1.0,
                                                                  STD_FLOOR)
                        for j, n in enumerate(names)], dtype=np.float64)
        meta = meta_features(names, candidate.meta, mean, std)
        known = self.fab.ids(self.slot_t)
        fallback = known.mean(0) if known.shape[0] else torch.zeros(self.fab.id_dim, device=self.device)
        ids = torch.stack([known[pos[n]] if n in pos else fallback for n in names]) if names else known[:0]
        norm = (*self._affine(mean, std), self._tensor(meta), o_shift, o_inv)
        out = []
        for sl in self._chunks(o.shape[0]):
            f = torch.from_numpy(vals[sl].astype(np.float32)).to(self.device)
            out.append(self.forward(f, torch.from_numpy(o[sl]).to(self.device), norm, ids=ids)[0].cpu())
        return torch.cat(out) if out else torch.zeros(0)

    # ---------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {"slots": dict(self.slots), "generation": self.generation, "fab": self.fab.state_dict(),
                "vpm": self.vpm.state_dict(), "tce": self.tce.state_dict(), "opt": self.opt.state_dict(),
                "input_snapshot": None if self.snapshot is None else asdict(self.snapshot)}

    def load_weights(self, state: dict[str, Any]) -> None:
        """The weights, optimiser state and input snapshot of a checkpoint; the slots and generation
        must have been restored (and the networks built) first."""
        if self.fab.id_slots != state["fab"]["id_table"].shape[0]:
            raise ValueError("checkpoint HARS ID table size does not match")
        self.fab.load_state_dict(state["fab"])
        self.vpm.load_state_dict(state["vpm"])
        self.tce.load_state_dict(state["tce"])
        self.opt.load_state_dict(state["opt"])
        self.weights_changed()
        snap = state.get("input_snapshot")
        self.snapshot = None if snap is None else InputSnapshot(**snap)
