"""MIRA's outer loop (Algorithm 3, lines 14-29) as a trainer hook: monitor every ΔT steps, reframe on
a trigger, and hand an accepted program to the inner loop.

Each cycle the hook rolls out held-out episodes with the current policy frozen (deterministic, fixed
episode seeds: the documented protocol), evaluates on those states what the monitor needs — policy
statistics of this cycle's and the previous cycle's policy on the *same* states, Φ(s), the attention
over factors, Φ(s') and the reward Φ is aligned to for the residual (RPE), and a value a state can
carry — and packs them into a :class:`~mira.mcm.records.CycleSnapshot`.

Which value. In the episodic setting the extrinsic reward is 0 on every step but the last, so its
discounted return-to-go from state s_t is γ^(T−t)·R: a function of the time left and of the episode's
return, the same for every state of an episode. Ranking states by it (SRR's proxy-efficacy labels)
or correlating Φ with it (PVC) measures "how near the end", not "how good a state". Instead the value
of a held-out state is the discounted return-to-go of the *decomposed* reward r̂ (HARS's head, fitted
to episodic returns only) along the frozen policy's own rollout: a Monte-Carlo estimate of V^π of r̂,
which is what Φ approximates under decomposed alignment and what the head says the return is made
of. It is used for PVC, for SRR's value-quantile labels and its Spearman check. Before the head's
first fit r̂ is 0 and so is every value (PVC then reads 0).
On a trigger (or, in the no-MCM ablation, on a fixed schedule) SRR proposes, checks and maybe
accepts a new program; on acceptance HARS re-initialises ϕ, φ and recomputes the buffer's factors
while θ and ψ are kept, and the monitor starts its cooldown; on abstention it backs off.

A plateau (:mod:`mira.mcm.plateau`: the held-out return flat, the episodes settled in a narrow band of the
card's ``band_feature``) is the monitor's other cause: SRR is asked for a way out, which the offline engineer
answers with a bounded SHAPE potential above the band. An escape installed that way is on probation: if the
held-out return has not risen by ``plateau.MIN_RISE`` over the plateau's median after ``K_cool`` cycles, its
SHAPE factors are removed again (the paper's back-off), as a new program version.

Ablations (section 5.4): ``no-srr`` runs the monitor and logs it but never edits; ``no-mcm`` calls
SRR every ``PERIODIC_CYCLES`` cycles (at most ``PERIODIC_MAX`` times), without diagnostic evidence.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch

from mira.engineer.backends import backend_state_dict, load_backend_state_dict
from mira.engineer.srr_prompt import Evidence
from mira.factors.program import FactorProgram, code_diff
from mira.llm.base import LLMBackend
from mira.loop.hooks import CycleContext
from mira.loop.rollout import discounted_return_to_go
from mira.mcm.band import stagnation_band
from mira.mcm.monitor import MetacognitiveMonitor
from mira.mcm.plateau import MIN_RISE, Plateau, PlateauDetector, first_states, late_states
from mira.mcm.records import CycleSnapshot, MCMResult
from mira.outer.config import OuterLoopConfig
from mira.outer.records import CycleRecords
from mira.outer.repair import StructuralCheck
from mira.runio.atomic import atomic_write_json, atomic_write_text
from mira.runio.failpoints import failpoint
from mira.runio.rundir import RunDir
from mira.shaping.attribution import ReturnAttribution
from mira.shaping.factors import ProgramFactorSource
from mira.shaping.source import HarsReward
from mira.srr.hypotheses import EditSurrogate
from mira.srr.reframe import Reframer, SRRDecision
from mira.tasks.card import TaskCard

log = logging.getLogger(__name__)

ABLATIONS = ("full", "no-mcm", "no-srr")
"""``full`` (MCM + SRR), ``no-mcm`` (periodic, unguided SRR) or ``no-srr`` (diagnosis only)."""
HOLDOUT_MAX_STATES = 1000
"""At most this many held-out states enter the diagnostics (evenly subsampled): bounds a cycle's cost."""
PERIODIC_CYCLES = 10
"""no-mcm: call SRR every this many cycles, about as often as MIRA's triggers can come (each starts a cooldown
of ``K_cool`` = 10 cycles)."""
PERIODIC_MAX = 5
"""no-mcm: at most this many periodic interventions (match MIRA's median trigger count)."""


class MiraOuterLoop:
    def __init__(
        self,
        config: OuterLoopConfig,
        card: TaskCard,
        hars: HarsReward,
        backend: LLMBackend | None,
        program: FactorProgram,
        action_dim: int,
        followups: int = 0,
        *,
        gamma: float,
        ablation: str = "full",
        budget: int | None = None,
    ) -> None:
        """``gamma`` is the agent's discount (d_RPE's target must use the trainer's γ); ``ablation`` one of
        :data:`ABLATIONS`, from the method name; ``budget`` the run's total steps (None: unbounded), so that
        no escape is installed that its probation could not judge before the run ends."""
        if ablation not in ABLATIONS:
            raise ValueError(f"unknown outer-loop ablation {ablation!r}")
        self.config = config
        self.ablation = ablation
        self.budget = budget
        if config.mcm.delta_t is None:
            raise ValueError("the outer loop needs its cycle length: resolve mcm.delta_t (None = one episode) first")
        self.interval: int = config.mcm.delta_t
        self.card = card
        self.hars = hars
        self.backend = backend
        self.program = program
        self.monitor = MetacognitiveMonitor(config.mcm, gamma=gamma)
        self.surrogate = EditSurrogate(lambda_comp=config.srr.lambda_comp)
        self.reframer = None if backend is None else Reframer(config.srr, card, backend, action_dim,
                                                                      self.surrogate, followups)
        self.cycle = 0
        self.interventions = 0
        self.prev_actor: dict[str, torch.Tensor] | None = None
        self.pending_observation: dict[str, Any] | None = None
        self.structural = StructuralCheck(card, hars)
        self.plateau = None if card.band_feature is None else PlateauDetector(card.band_feature)
        self.escape: dict[str, Any] | None = None
        """The escape on probation: its factors, the plateau's median return, the cycle it is judged at and the
        held-out returns since it was installed."""
        self._records = CycleRecords()

    # ------------------------------------------------------------------------------------------- cycle
    def on_cycle(self, ctx: CycleContext) -> dict[str, float]:
        cfg = self.config
        rollout = ctx.rollout(cfg.holdout_episodes, 0)
        keep = np.linspace(0, len(rollout.obs) - 1, min(HOLDOUT_MAX_STATES, len(rollout.obs))).astype(int)
        obs, next_obs = rollout.obs[keep], rollout.next_obs[keep]
        obs_t = torch.as_tensor(obs)
        stats = ctx.agent.policy_stats(obs_t)
        prev_mean = prev_log_std = None
        if self.prev_actor is not None:
            prev = ctx.agent.policy_stats_with(self.prev_actor, obs_t)
            prev_mean, prev_log_std = prev.mean, prev.log_std
        self.prev_actor = ctx.agent.actor_state()

        phi_s = self.hars.potential(obs).cpu().numpy().astype(np.float64)
        phi_next = self.hars.potential(next_obs).cpu().numpy().astype(np.float64)
        terminal = rollout.terminated[keep].astype(np.float64)
        r_hat = self.hars.decomposed_reward(rollout.obs, rollout.actions, rollout.next_obs)
        values = discounted_return_to_go(r_hat, rollout.episode_index, self.hars.gamma)
        aligned_to = rollout.r_ext if self.hars.config.alignment == "episodic" else r_hat
        attention = self.hars.attention(obs)
        recent = float(rollout.returns.mean())
        snapshot = CycleSnapshot(
            step=ctx.step, policy_mean=stats.mean.astype(np.float64), policy_log_std=stats.log_std.astype(np.float64),
            squashed=stats.squashed, prev_policy_mean=prev_mean, prev_policy_log_std=prev_log_std,
            phi_eval=phi_s, value_eval=values[keep], attention_mean=attention,
            phi_s=phi_s, r_ext=aligned_to[keep], phi_next=phi_next * (1.0 - terminal), terminal=terminal,
            smoothed_return=recent, factor_ids_changed=False,
        )
        result = self.monitor.diagnose(snapshot)
        plateau = self._watch_plateau(ctx, rollout, recent, result)
        # The unguided ablation gets no evidence of any kind, this included.
        attribution = self.structural.observe() if cfg.repair and self.ablation != "no-mcm" else None
        self._log(ctx, result, attribution)
        self._observe_pending(result)
        # The head's current fit, whatever program it is over (train.csv's columns are the first program's).
        atomic_write_json(ctx.run.path / "decomposition.json",
                          {"step": ctx.step, "version": self.program.version, **self.hars.head.describe()})

        structural = cfg.repair and self.ablation != "no-mcm" and self.structural.triggered
        if structural and attribution is not None and attribution.best is not None:
            best = attribution.best
            shape = best.feature if best.form == "value" else f"-{best.feature}²"
            log.info("step %d: the returns show a structural flaw: with %s the program's factors would explain "
                     "them out of sample with R² %.3f instead of %.3f (%d cycles in a row)", ctx.step, shape,
                     best.r2, attribution.program_r2, self.structural.streak)
        escaping = plateau is not None and self.ablation == "full" and self.escape is None
        if escaping and not self._judgeable(ctx.step):
            escaping = False
            log.info("step %d: no escape: its probation (%d cycles) would end after the run's last step %d",
                     ctx.step, self.config.mcm.k_cool, self.budget)
            self._record(ctx, "too_late")
        wants_srr = False
        if self.ablation == "full":
            wants_srr = result.trigger or structural or escaping
        elif self.ablation == "no-mcm":
            wants_srr = (self.cycle + 1) % PERIODIC_CYCLES == 0 and self.interventions < PERIODIC_MAX
        decision = None
        if result.trigger:
            why = ", ".join(f"{str(c['metric']).upper()} {c['value']:+.2f} ({c['reading']})"
                            for c in result.evidence()["contributors"][:2])
            log.info("step %d: the monitor triggered (S = %.3g above %.3g): %s", ctx.step, float(result.score),
                     float(result.threshold), why or "no single leading metric")
        if wants_srr and self.reframer is not None:
            # A rejection makes the monitor harder to trigger, unless the structural check alone asked.
            backoff_monitor = result.trigger or self.ablation != "full" or not (structural or escaping)
            cause = ("anomaly" if result.trigger else "structural" if structural else "plateau" if escaping
                     else "periodic")
            decision = self._reframe(ctx, result, rollout, keep, values[keep], attention, recent, attribution,
                                     backoff_monitor, cause, plateau if cause == "plateau" else None)
        self.cycle += 1
        out = {"S": float(result.score) if np.isfinite(result.score) else float("nan"),
               "trigger": float(result.trigger), "version": float(self.program.version)}
        if decision is not None:
            out["accepted"] = float(decision.accepted)
        return out

    def _judgeable(self, step: int) -> bool:
        """Whether an escape installed at ``step`` is judged before the run ends: one left on probation at the
        end would be in the final figures unjudged, with its cost and none of the back-off."""
        return self.budget is None or step + self.config.mcm.k_cool * self.interval <= self.budget

    def _watch_plateau(self, ctx: CycleContext, rollout: Any, recent: float, result: MCMResult) -> Plateau | None:
        """Feed the plateau detector this cycle's held-out episodes; judge an escape on probation."""
        if self.plateau is None or self.ablation == "no-mcm":
            return None
        if self.escape is not None:
            self._judge_escape(ctx, recent)
            if self.escape is not None:  # still on probation: its returns are not a stall of the program before it
                return None
        feature = self.card.feature_values(rollout.obs)[self.plateau.feature]
        visited = (float(np.percentile(feature, 1)), float(np.percentile(feature, 99)))
        d = result.evidence()["d"]
        found = self.plateau.observe(ctx.step, recent, late_states(feature, rollout.episode_index), visited,
                                     d.get("peg"), d.get("rpe"),
                                     float(np.median(first_states(feature, rollout.episode_index))))
        if found is not None:
            log.info("step %d: learning has stalled: held-out return %.6g against %.6g before (%+.1f%%), episodes "
                     "settled at %s = %.4g ± %.3g", ctx.step, found.recent_median, found.previous_median,
                     100 * found.rise, found.feature, found.center, found.halfwidth)
            self._record(ctx, "plateau", feature=found.feature, center=found.center, halfwidth=found.halfwidth,
                         median=found.recent_median, before=found.previous_median, rise=found.rise)
        return found

    def _judge_escape(self, ctx: CycleContext, recent: float) -> None:
        """After ``K_cool`` cycles, keep an escape whose held-out returns rose above the plateau's, else remove it."""
        escape = self.escape
        assert escape is not None
        escape["returns"].append(recent)
        if self.cycle < escape["due_cycle"]:
            return
        self.escape = None
        after = float(np.median(escape["returns"]))
        rise = (after - escape["plateau_median"]) / max(abs(escape["plateau_median"]), 1e-8)
        verdict = {"step": ctx.step, "plateau_median": escape["plateau_median"], "median_since": after, "rise": rise,
                   "factors": escape["factors"], "kept": rise >= MIN_RISE}
        atomic_write_json(ctx.run.path / escape["folder"] / "probation.json", verdict)
        if rise >= MIN_RISE:
            log.info("step %d: the escape paid (held-out return %+.1f%% over the plateau): kept", ctx.step, 100 * rise)
            assert self.plateau is not None
            self.plateau.reset()
            self._record(ctx, "escape_kept", median=after, before=escape["plateau_median"], rise=rise)
            return
        old = self.program
        self._switch(ctx.run, old.with_factors([f for f in old.factors if f.name not in escape["factors"]],
                                               version=old.version + 1, parent_version=old.version, edits=(),
                                               rationale=f"rolled back {', '.join(escape['factors'])}: the escape "
                                               f"did not pay within {self.config.mcm.k_cool} cycles "
                                               f"({100 * rise:+.1f}%)", diff=""))
        assert self.plateau is not None
        self.plateau.reset()
        log.info("step %d: the escape did not pay (held-out return %+.1f%% over the plateau): rolled back to "
                 "program v%d without %s", ctx.step, 100 * rise, self.program.version, ", ".join(escape["factors"]))
        self._record(ctx, "escape_rolled_back", median=after, before=escape["plateau_median"], rise=rise)

    def _record(self, ctx: CycleContext, event: str, **row: Any) -> None:
        """One line of ``plateau.csv`` (:class:`CycleRecords`)."""
        self._records.plateau(ctx.run.path, ctx.step, event, self.program.version, **row)

    def _reframe(self, ctx: CycleContext, result: MCMResult, rollout: Any, keep: np.ndarray, values: np.ndarray,
                 attention: dict[str, float], recent: float, attribution: ReturnAttribution | None,
                 backoff_monitor: bool, cause: str, plateau: Plateau | None = None) -> SRRDecision:
        assert self.reframer is not None
        guided = self.ablation == "full"
        band = None
        if plateau is not None:
            band = {"feature": plateau.feature, "center": plateau.center, "halfwidth": plateau.halfwidth}
        elif self.card.band_feature is not None:
            center, half = stagnation_band(self.card.feature_values(rollout.obs)[self.card.band_feature])
            band = {"feature": self.card.band_feature, "center": center, "halfwidth": half}
        ev = result.evidence()
        evidence = Evidence(
            step=ctx.step, d=ev["d"], d_raw=ev["d_raw"], score=ev["score"], threshold=ev["threshold"],
            gradient=ev["gradient"], contributors=ev["contributors"], recent_return=recent,
            baseline_return=float(result.baseline), stagnation_band=band, attention=attention, guided=guided,
            decomposition=self.hars.head.describe(),
            return_attribution=None if attribution is None or not guided else attribution.as_dict(), cause=cause,
            plateau=None if plateau is None else {
                **plateau.as_dict(),
                "reward_per_step": recent / max(1.0, float(len(rollout.obs)) / max(1, len(rollout.returns)))},
        )
        folder = ctx.run.interventions / f"{self.interventions:03d}-step{ctx.step}"
        self.interventions += 1

        def proxy(program: FactorProgram, states: np.ndarray) -> np.ndarray:
            source = ProgramFactorSource(program, self.card)
            return self.hars.proxy_potential(source, states).cpu().numpy()

        # The sandbox runs on a spread of real states from the replay buffer (a fixed-seed sample).
        rows = np.random.default_rng(ctx.step).integers(0, ctx.buffer.size, size=min(512, ctx.buffer.size))
        sandbox_obs = ctx.buffer.obs[rows].numpy().astype(np.float64)
        sandbox_actions = ctx.buffer.action[rows].numpy().astype(np.float64)
        failpoint("srr.before_call")
        def explain(program: FactorProgram) -> float:
            return self.structural.explain(ProgramFactorSource(program, self.card))

        decision = self.reframer.reframe(folder, self.program, evidence, rollout.obs[keep], values,
                                         sandbox_obs, sandbox_actions, proxy, seed=ctx.step,
                                         explain=explain if attribution is not None else None)
        self.structural.rest()
        if decision.accepted:
            old = self.program
            self._switch(ctx.run, decision.program)
            self.monitor.on_edit_accepted()
            self.pending_observation = {"operators": decision.operators, "d_before": result.d.tolist(),
                                        "due_cycle": self.cycle + self.config.mcm.k_cool}
            if plateau is not None:
                added = sorted({f.name for f in self.program.shape_factors} - {f.name for f in old.shape_factors})
                self.escape = {"factors": added, "plateau_median": plateau.recent_median, "returns": [],
                               "due_cycle": self.cycle + self.config.mcm.k_cool, "folder": folder.relative_to(
                                   ctx.run.path).as_posix()}
            changed = [ln for ln in code_diff(old, self.program).splitlines()
                       if ln.startswith("+") and not ln.startswith("+++") and ln[1:].strip()]
            log.info("step %d: installed program v%d (%s, %s)%s", ctx.step, self.program.version, decision.reason,
                     "+".join(decision.operators) or "edit", f": {changed[0][1:].strip()}" if changed else "")
        elif decision.backoff:
            if backoff_monitor:
                self.monitor.on_backoff(self.config.srr.delta_q)
            log.info("step %d: backed off, program v%d kept (%s)", ctx.step, self.program.version, decision.reason)
        return decision

    def _observe_pending(self, result: MCMResult) -> None:
        """Finite-difference update of J_F once an accepted edit has had its cooldown to take effect."""
        pending = self.pending_observation
        if pending is None or self.cycle < pending["due_cycle"]:
            return
        self.surrogate.observe(pending["operators"], np.asarray(pending["d_before"]), result.d)
        self.pending_observation = None

    def _log(self, ctx: CycleContext, result: MCMResult, attribution: ReturnAttribution | None) -> None:
        self._records.diagnostics(ctx.run.path, ctx.step, result, self.program.version, attribution,
                                  self.structural.triggered)

    # ------------------------------------------------------------------------------------- checkpoint
    def _switch(self, run: RunDir, new: FactorProgram) -> None:
        """Make ``new`` the program in force: its version saved with the diff, then the shaping switched to it."""
        old, self.program = self.program, new
        save_program_version(run.programs, old, new)
        failpoint("program.saved")
        self.hars.set_program(ProgramFactorSource(new, self.card))
        failpoint("program.applied")

    def on_fork(self, run: RunDir, program: Any | None) -> None:
        """Install ``program`` (``mira train --fork-program``) as the next version, as an accepted edit is."""
        if program is not None:
            v = self.program.version
            self._switch(run, program.with_factors(program.factors, version=v + 1, parent_version=v, edits=(),
                                                   diff="", rationale=f"installed at the fork: {program.rationale}"))
            log.info("fork: program v%d installed (%s)", v + 1, ", ".join(f.name for f in program.factors))

    def state_dict(self) -> dict[str, Any]:
        return {"cycle": self.cycle, "interventions": self.interventions, "program": self.program.to_json(),
                "monitor": self.monitor.state_dict(), "structural": self.structural.state_dict(),
                "surrogate": self.surrogate.state_dict(), "prev_actor": self.prev_actor,
                "pending": self.pending_observation,
                "llm": backend_state_dict(self.backend) if self.backend is not None else {},
                "refused": self.reframer.refused if self.reframer is not None else [],
                "plateau": None if self.plateau is None else self.plateau.state_dict(), "escape": self.escape}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.cycle, self.interventions = state["cycle"], state["interventions"]
        self.program = FactorProgram.from_json(state["program"])
        self.monitor.load_state_dict(state["monitor"])
        self.structural.load_state_dict(state.get("structural", {}))
        self.surrogate.load_state_dict(state["surrogate"])
        self.prev_actor = state["prev_actor"]
        self.pending_observation = state["pending"]
        if self.backend is not None:
            load_backend_state_dict(self.backend, state["llm"])
        if self.reframer is not None:
            self.reframer.refused = list(state.get("refused", []))
        if self.plateau is not None and state.get("plateau") is not None:
            self.plateau.load_state_dict(state["plateau"])
        self.escape = state.get("escape")


def save_program_version(directory: Any, old: FactorProgram | None, new: FactorProgram) -> None:
    """``programs/vNNN.json`` and its unified diff to the previous version."""
    atomic_write_json(directory / f"v{new.version:03d}.json", new.to_json())
    if old is not None:
        atomic_write_text(directory / f"v{new.version:03d}.diff", code_diff(old, new))
