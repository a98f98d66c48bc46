"""SRR.Reframe (Algorithm 2): evidence → hypotheses → LLM candidates → checks → decision.

Each candidate passes, in order, the parser (schema and factor model), static integrity (AST whitelist),
sandbox realizability (real states, separate process, limits it cannot lift) and proxy efficacy (ROC-AUC
> 0.5 with permutation p < 0.05 on value-quantile labels, and J_SRR > 0) or, where the stored episodes
are at hand, return explanation (the candidate's out-of-sample R² of the episodic returns above the
current program's by ``MIN_R2_GAIN``: the test a structural repair can pass, see
:mod:`mira.shaping.attribution`, where these thresholds live). Where the returns are at hand they also
veto: a candidate whose R² is below the current program's by more than ``MAX_R2_LOSS`` (or, for a
program that explains the returns almost exactly, by more than ``MAX_UNEXPLAINED_GROWTH`` times what it
leaves unexplained) is refused whatever its proxy test says (the AUC labels come from the current
program, the returns from the task). A candidate that changes only SHAPE factors (shaping terms outside the
fitted reward, :mod:`mira.shaping.source`) is judged as what it is: it leaves the program's fit to the
returns and its potential unchanged by construction, so neither the returns nor the proxy test can say
anything of it; it passes when each SHAPE factor declares a finite range, at most ``MAX_SHAPE_STEPS``
steps of the run's reward wide, and keeps to it on the held-out states (a bounded potential), after the
same parser, static checks and sandbox. The best passing candidate (by R² gain, then J_SRR) is accepted;
if none passes, SRR abstains and the caller backs off. A failing LLM is a recorded, failed intervention,
never a crash. Every step is written into the intervention's folder as it happens.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mira.engineer.admission import admit_program
from mira.engineer.dialogue import Verdict, converse
from mira.engineer.srr_candidates import Candidate, parse_candidates
from mira.engineer.srr_prompt import MAX_SHAPE_STEPS, Evidence, build_srr_request
from mira.factors.checker import parse_range_hint
from mira.factors.program import FactorProgram, ProgramParseError, code_diff
from mira.llm.base import LLMBackend, LLMError
from mira.runio.atomic import atomic_write_json, atomic_write_text
from mira.runio.failpoints import failpoint
from mira.shaping.attribution import MAX_R2_LOSS, MAX_UNEXPLAINED_GROWTH, MIN_R2_GAIN
from mira.shaping.factors import ProgramFactorSource
from mira.srr.config import SRRConfig
from mira.srr.efficacy import proxy_efficacy
from mira.srr.hypotheses import METRICS, OPERATORS, EditSurrogate, complexity, rule_hypotheses
from mira.tasks.card import TaskCard

log = logging.getLogger(__name__)

PERMUTATIONS = 1000
"""Permutations of the AUC and Spearman tests: resolves p-values down to 1/1001, well below ``max_p_value``."""
LABEL_QUANTILES = (0.3, 0.7)
"""States at or below the first value quantile are negatives, at or above the second positives: the middle
40%, whose ranking is noise, is left out."""

ProxyPotential = Callable[[FactorProgram, np.ndarray], np.ndarray]
"""``proxy(program, obs[N, obs_dim]) -> Φ̃[N]``: a candidate's PHI factors through the frozen FAB/VPM."""
ReturnExplanation = Callable[[FactorProgram], float]
"""``explain(program) -> R²``: out-of-sample R² of the stored episodes' returns decomposed over a program."""


@dataclass
class SRRDecision:
    accepted: bool
    program: FactorProgram
    reason: str
    backoff: bool
    failed: bool = False
    candidate: int | None = None
    operators: list[str] = field(default_factory=list)
    j_srr: float | None = None
    folder: str = ""

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in asdict(self).items() if k != "program"}
        out["version"] = self.program.version
        return out


class Reframer:
    def __init__(
        self,
        config: SRRConfig,
        card: TaskCard,
        backend: LLMBackend,
        action_dim: int,
        surrogate: EditSurrogate | None = None,
        followups: int = 0,
        *,
        permutations: int | None = None,
    ) -> None:
        """``permutations``: of the efficacy tests (None: :data:`PERMUTATIONS`; fewer make tests fast)."""
        self.config = config
        self.permutations = PERMUTATIONS if permutations is None else permutations
        self.followups = followups
        self.refused: list[dict[str, Any]] = []
        """The last intervention's refused candidates and why: the next prompt tells the model."""
        self.card = card
        self.backend = backend
        self.action_dim = action_dim
        self.surrogate = surrogate or EditSurrogate(lambda_comp=config.lambda_comp)
        self._reward_per_step = 0.0  # of the request being judged: bounds a SHAPE factor's size

    def reframe(
        self,
        folder: Path,
        program: FactorProgram,
        evidence: Evidence,
        eval_obs: np.ndarray,
        eval_values: np.ndarray,
        sandbox_obs: np.ndarray,
        sandbox_actions: np.ndarray,
        proxy: ProxyPotential,
        seed: int,
        explain: ReturnExplanation | None = None,
    ) -> SRRDecision:
        cfg = self.config
        folder.mkdir(parents=True, exist_ok=True)
        poor = evidence.poor_return
        # The rules read the monitor's diagnostics: they say something only where the monitor asked. For a
        # structural trigger the returns' evidence is the reason, and readings of the dynamics beside it
        # would contradict it (in the prompt and in the run's record alike).
        hypotheses = rule_hypotheses(evidence.d, poor) if evidence.guided and evidence.cause == "anomaly" else []
        atomic_write_json(folder / "evidence.json", {**evidence.as_dict(),
                                                     "hypotheses": [h.as_dict() for h in hypotheses]})
        request = build_srr_request(self.card, program, evidence, hypotheses, cfg.max_candidates, OPERATORS,
                                    self.action_dim, self.refused)
        atomic_write_json(folder / "request.json", request.to_dict())

        started = time.monotonic()
        replies: list[list[Candidate]] = []  # each reply's candidates, admitted or not, for the records

        def judge(text: str) -> Verdict[list[Candidate]]:
            verdict = self._admit_reply(text, program, sandbox_obs, sandbox_actions)
            replies.append(verdict.value or [])
            return verdict if any(c.admitted for c in verdict.value or []) else Verdict(None, verdict.errors,
                                                                                       verdict.record)

        try:
            dialogue = converse(self.backend, request, judge, self.followups)
        except LLMError as exc:
            return self._finish(folder, SRRDecision(False, program, f"LLM call failed: {type(exc).__name__}: {exc}",
                                                    backoff=True, failed=True))
        except Exception as exc:  # a backend's own bug must not end hours of training: record it instead
            log.exception("SRR: the LLM backend raised an unexpected error")
            return self._finish(folder, SRRDecision(False, program, f"LLM call failed: {type(exc).__name__}: {exc}",
                                                    backoff=True, failed=True))
        for i, attempt in enumerate(dialogue.attempts[:-1]):
            atomic_write_text(folder / f"response-{i + 1}.txt", attempt.content)
        atomic_write_text(folder / "response.txt", dialogue.attempts[-1].content)
        if len(dialogue.attempts) > 1 or not dialogue.value:
            atomic_write_json(folder / "attempts.json", [a.as_dict() for a in dialogue.attempts])
        failpoint("srr.after_reply")
        candidates = replies[-1]
        if not candidates:  # the last reply as a whole could not be read
            reason = "; ".join(dialogue.attempts[-1].errors)
            self.refused = [{"step": evidence.step, "candidate": None, "operators": [], "reason": reason}]
            return self._finish(folder, SRRDecision(False, program, f"reply rejected before any check: {reason}",
                                                    backoff=True, failed=True))

        direction = None
        if evidence.guided and any(evidence.gradient.values()):
            direction = np.array([evidence.gradient.get(m, 0.0) for m in METRICS])
        base_r2 = _safe_r2(explain, program) if explain is not None else None
        plateau = evidence.plateau or {}
        self._reward_per_step = abs(float(plateau.get("reward_per_step",
                                                      evidence.recent_return / max(1, self.card.eval_horizon))))
        shortlist: list[tuple[tuple[float, float], Candidate]] = []
        for cand in candidates:
            passed, j_srr = self._validate(cand, program, eval_obs, eval_values, proxy, direction, seed, explain,
                                           base_r2)
            gain = cand.verdicts.get("returns", {}).get("gain")
            if passed and j_srr is not None:
                shortlist.append(((gain if gain is not None and np.isfinite(gain) else -np.inf, j_srr), cand))
            eff = cand.verdicts.get("efficacy")
            if "shaping" in cand.verdicts:
                verdict = "shaping term, bounded: passed" if passed else cand.verdicts.get("rejected", "rejected")
            elif eff:  # it reached the proxy-efficacy check: its figures say why it passed or not
                r2 = "" if gain is None else f", return R² {gain:+.3f}"
                verdict = (f"AUC {eff['auc']:.3f}, p {eff['auc_p']:.3g}, J_SRR {eff['j_srr']:.3f}{r2}: "
                           + ("passed" if passed else "rejected"))
            else:
                verdict = cand.verdicts.get("rejected", cand.error or "rejected")
            log.info("step %d: candidate %d [%s]: %s", evidence.step, cand.index, "+".join(cand.operators) or "?",
                     verdict)
        atomic_write_json(folder / "candidates.json", [self._candidate_record(c) for c in candidates])
        log.info("SRR: %d candidates, %d passed, %.1f s", len(candidates), len(shortlist), time.monotonic() - started)
        self.refused = [{"step": evidence.step, "candidate": c.index, "operators": c.operators,
                         "targets": sorted({t for e in c.edits if isinstance(e, dict)
                                            for t in e.get("targets", []) if isinstance(t, str)}),
                         "reason": c.error or c.verdicts.get("rejected", "rejected")}
                        for c in candidates if c.error or "rejected" in c.verdicts]
        if not shortlist:
            reasons = "; ".join(c.error or c.verdicts.get("rejected", "rejected") for c in candidates)
            return self._finish(folder, SRRDecision(False, program, f"no candidate passed: {reasons}", backoff=True))
        (_, j_best), best = max(shortlist, key=lambda t: t[0])
        assert best.program is not None
        atomic_write_text(folder / "accepted.diff", code_diff(program, best.program))
        return self._finish(folder, SRRDecision(True, best.program, f"accepted candidate {best.index}"
                                                f"{choice_reason(shortlist, best.index)}", backoff=False,
                                                candidate=best.index, operators=best.operators, j_srr=j_best))

    # ------------------------------------------------------------------------------------------------
    def _validate(
        self,
        cand: Candidate,
        current: FactorProgram,
        obs: np.ndarray,
        values: np.ndarray,
        proxy: ProxyPotential,
        direction: np.ndarray | None,
        seed: int,
        explain: ReturnExplanation | None = None,
        base_r2: float | None = None,
    ) -> tuple[bool, float | None]:
        cfg = self.config
        if not cand.admitted:
            return False, None
        assert cand.program is not None
        if _changes_only_shaping(current, cand.program):
            return self._validate_shaping(cand, current, obs, direction)
        try:
            phi = np.asarray(proxy(cand.program, obs), dtype=np.float64)
        except Exception as exc:  # a proxy failure rejects the candidate, it never stops training
            cand.verdicts["rejected"] = f"proxy potential failed: {type(exc).__name__}: {exc}"
            return False, None
        lo, hi = LABEL_QUANTILES
        eff = proxy_efficacy(phi, values, lo_q=lo, hi_q=hi, n_perm=self.permutations, seed=seed)
        code_growth = sum(len(f.code) for f in cand.program.factors) - sum(len(f.code) for f in current.factors)
        comp = complexity(len(cand.operators), len(cand.program.factors) - len(current.factors), code_growth)
        j_srr = self.surrogate.score(cand.operators, direction, comp)
        predicted = dict(zip(METRICS, self.surrogate.predict(cand.operators).round(4).tolist(), strict=True))
        cand.verdicts["efficacy"] = {**eff.as_dict(), "j_srr": j_srr, "complexity": comp,
                                     "predicted_delta_d": predicted}
        ok = eff.auc > cfg.min_auc and eff.auc_p < cfg.max_p_value and j_srr > 0
        explains = harms = False
        if explain is not None and base_r2 is not None and np.isfinite(base_r2):
            r2 = _safe_r2(explain, cand.program)
            gain = r2 - base_r2
            explains = bool(np.isfinite(gain) and gain >= MIN_R2_GAIN)
            allowed = allowed_r2_loss(base_r2, MAX_R2_LOSS, MAX_UNEXPLAINED_GROWTH)
            harms = bool(np.isfinite(gain) and gain < -allowed)
            cand.verdicts["returns"] = {"cv_r2": r2, "current_cv_r2": base_r2, "gain": gain,
                                        "allowed_loss": allowed, "passed": explains, "harms": harms}
        if harms:
            assert base_r2 is not None  # harms is only set where the current R² is known
            cand.verdicts["rejected"] = (f"return explanation: out-of-sample R² of the returns {_r2_text(base_r2)} -> "
                                         f"{_r2_text(base_r2 + cand.verdicts['returns']['gain'])} (a loss above "
                                         f"{allowed:.3g}): the program would express what the task pays "
                                         "for worse than the current one")
            return False, j_srr
        if not (ok or explains):
            cand.verdicts["rejected"] = (f"proxy efficacy: AUC {eff.auc:.3f} (p {eff.auc_p:.3g}), J_SRR {j_srr:.3f} "
                                         f"(needs AUC > {cfg.min_auc}, p < {cfg.max_p_value}, J_SRR > 0)"
                                         + ("" if "returns" not in cand.verdicts else
                                            f"; return R² gain {cand.verdicts['returns']['gain']:+.3f} "
                                            f"(or at least {MIN_R2_GAIN})"))
        return ok or explains, j_srr

    def _validate_shaping(self, cand: Candidate, current: FactorProgram, obs: np.ndarray,
                          direction: np.ndarray | None) -> tuple[bool, float | None]:
        """A shaping-only candidate: every SHAPE factor bounded by a finite declared range, and within it on
        the held-out states."""
        assert cand.program is not None
        comp = complexity(len(cand.operators), len(cand.program.factors) - len(current.factors),
                          sum(len(f.code) for f in cand.program.factors) - sum(len(f.code) for f in current.factors))
        j_srr = self.surrogate.score(cand.operators, direction, comp)
        values = ProgramFactorSource(cand.program, self.card).compiled.shape(self.card.state_view(obs))
        problems = []
        for j, f in enumerate(cand.program.shape_factors):
            bounds = parse_range_hint(f.range_hint) if f.range_hint else None
            if bounds is None or not all(np.isfinite(bounds)):
                problems.append(f"{f.name}: a SHAPE factor must declare a finite range_hint (a bounded potential)")
                continue
            lo, hi = bounds
            if hi - lo > MAX_SHAPE_STEPS * self._reward_per_step:
                problems.append(f"{f.name}: its declared range [{lo:.4g}, {hi:.4g}] is wider than {MAX_SHAPE_STEPS:g} "
                                f"steps of the run's reward ({self._reward_per_step:.4g} per step)")
                continue
            slack = 1e-6 * max(1.0, hi - lo)
            seen = (float(values[:, j].min()), float(values[:, j].max())) if len(values) else (lo, hi)
            if seen[0] < lo - slack or seen[1] > hi + slack:
                problems.append(f"{f.name}: values [{seen[0]:.4g}, {seen[1]:.4g}] on the held-out states leave its "
                                f"declared range [{lo:.4g}, {hi:.4g}]")
        cand.verdicts["shaping"] = {"shape_only": True, "j_srr": j_srr, "complexity": comp,
                                    "problems": problems, "passed": not problems}
        if problems:
            cand.verdicts["rejected"] = "shaping term: " + "; ".join(problems)
            return False, j_srr
        return True, j_srr

    def _admit_reply(self, text: str, current: FactorProgram, sandbox_obs: np.ndarray,
                     sandbox_actions: np.ndarray) -> Verdict[list[Candidate]]:
        """Parse a reply into candidates and pass each through the parser, the static checks and the sandbox:
        the gates whose errors a model can fix. Efficacy is judged later, on the admitted ones only."""
        try:
            candidates = parse_candidates(text, current, self.config.max_candidates)
        except ProgramParseError as exc:
            return Verdict(None, [str(exc)], {"parsed": False, "error": str(exc)})
        # Factors the current program already has, unchanged, were admitted before: only what a candidate
        # changes or adds goes through the sandbox again.
        known = {(f.name, f.code) for f in current.factors}
        errors: list[str] = []
        for cand in candidates:
            if cand.program is None:
                cand.verdicts["rejected"] = f"parse: {cand.error}"
                errors.append(str(cand.error))
                continue
            changed = [f.name for f in cand.program.factors if (f.name, f.code) not in known]
            try:
                gates = admit_program(cand.program, self.card, states=sandbox_obs, actions=sandbox_actions,
                                      only=changed, timeout_s=self.config.sandbox_timeout_s)
            except Exception as exc:  # a fault of the checks must cost this candidate, never the reply
                log.exception("SRR: checking candidate %d failed", cand.index)
                cand.verdicts["rejected"] = f"the checks failed on it: {type(exc).__name__}: {exc}"
                errors.append(f"candidate {cand.index}: could not be checked ({type(exc).__name__}: {exc})")
                continue
            cand.verdicts["static"] = gates.static
            if gates.sandbox is not None:
                cand.verdicts["sandbox"] = gates.sandbox.to_dict()
            if not gates.ok:
                stage = "sandbox" if gates.sandbox is not None else "static integrity"
                cand.verdicts["rejected"] = f"{stage}: " + "; ".join(gates.errors)
                errors += [f"candidate {cand.index}: {e}" for e in gates.errors]
        record = {"parsed": True, "candidates": [{"index": c.index, "admitted": c.admitted,
                                                  "rejected": c.verdicts.get("rejected")} for c in candidates]}
        return Verdict(candidates, errors, record)

    @staticmethod
    def _candidate_record(c: Candidate) -> dict[str, Any]:
        return {"index": c.index, "operators": c.operators, "edits": c.edits, "parse_error": c.error,
                "program": None if c.program is None else c.program.to_json(), "verdicts": c.verdicts}

    @staticmethod
    def _finish(folder: Path, decision: SRRDecision) -> SRRDecision:
        decision.folder = str(folder)
        atomic_write_json(folder / "decision.json", decision.as_dict())
        return decision


def choice_reason(shortlist: list[tuple[tuple[float, float], Candidate]], chosen: int) -> str:
    """Why the chosen candidate won over the others that passed: candidates are ranked by the return R²
    they gain (the returns measure what the task pays for), then by J_SRR (the predicted diagnostic
    improvement), so a higher J_SRR loses to any larger R² gain."""
    if len(shortlist) < 2:
        return " (the only candidate that passed)"
    (gain, j), _ = next(t for t in shortlist if t[1].index == chosen)
    others = ", ".join(f"candidate {c.index}: R² {'n/a' if not np.isfinite(g) else f'{g:+.3f}'}, J_SRR {jj:.3f}"
                       for (g, jj), c in shortlist if c.index != chosen)
    if np.isfinite(gain):
        return f" (largest return R² gain, {gain:+.3f}, J_SRR {j:.3f}; ranked by R² gain, then J_SRR; {others})"
    return f" (highest J_SRR, {j:.3f}, no return R² measured; {others})"


def _changes_only_shaping(current: FactorProgram, candidate: FactorProgram) -> bool:
    """Whether ``candidate`` differs from ``current`` in its SHAPE factors alone (and does differ there)."""
    def fitted(p: FactorProgram) -> list[tuple[str, str, str]]:
        return [(f.name, f.type, f.code) for f in p.factors if f.type != "SHAPE"]

    def shaping(p: FactorProgram) -> list[tuple[str, str, str]]:
        return [(f.name, f.type, f.code) for f in p.shape_factors]

    return fitted(current) == fitted(candidate) and shaping(current) != shaping(candidate)


def allowed_r2_loss(current_r2: float, max_loss: float, max_unexplained_growth: float) -> float:
    """The largest fall of the returns' out-of-sample R² a candidate may cause: ``max_loss``, or
    ``max_unexplained_growth · (1 − current_r2)`` when the current program leaves less than that unexplained
    (the returns' noise, against which the tolerance guards, shrinks with what is left unexplained)."""
    return min(max_loss, max_unexplained_growth * max(1.0 - current_r2, 0.0))


def _r2_text(r2: float) -> str:
    """An R² with as many decimals as it takes to show how far from 1 it is."""
    return f"{r2:.3f}" if 1.0 - r2 >= 1e-3 else f"{r2:.6f}"


def _safe_r2(explain: ReturnExplanation, program: FactorProgram) -> float:
    """``explain(program)``, NaN when it fails: a measurement failure rejects a candidate, never the run."""
    try:
        return float(explain(program))
    except Exception:  # the program passed the sandbox; anything left is the measurement's problem
        log.exception("SRR: measuring a program's return explanation failed")
        return float("nan")
