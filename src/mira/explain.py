"""``mira explain RUN_DIR``: the story of a run in plain words, from its directory alone.

Which program versions there were and when, why each intervention happened (the monitor's evidence),
what SRR proposed and what each check said, what changed, and what the evaluation return did after.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.runio.csvlog import read_csv
from mira.runio.rundir import describe_status


def _load(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


def _mean_return(evals: list[dict[str, str]], lo: int, hi: int) -> float | None:
    vals = [float(r["return_mean"]) for r in evals if lo < int(r["step"]) <= hi]
    return sum(vals) / len(vals) if vals else None


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1f}"


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _decomposition_line(what: str, weights: dict[str, float], shares: dict[str, float], r2: float) -> str:
    """One return decomposition (HARS's head) in words: what the returns were found to be made of."""
    parts = ", ".join(f"{n} {float(w):+.3g}" + (f" ({100 * float(shares[n]):.0f}%)" if n in shares else "")
                      for n, w in weights.items())
    return (f"Return decomposition {what} (r̂ = Σ w·factor + bias fitted to episodic returns; weight and share "
            f"of r̂): {parts}; R² of returns {float(r2):.3f}.")


def _decomposition(run: Path) -> list[str]:
    """The latest decomposition: the outer loop's ``decomposition.json`` (whatever program it is over),
    else the last one logged in ``train.csv`` (a static program's)."""
    latest = _load(run / "decomposition.json")
    if latest and latest.get("episodes"):
        return [_decomposition_line(f"of program v{latest['version']} at step {latest['step']}",
                                    latest["weights"], latest.get("shares", {}), latest["r2"])]
    last = next((r for r in reversed(read_csv(run / "train.csv")) if r.get("decomp_r2")), None)
    if last is None:
        return []
    weights = {k[2:]: float(v) for k, v in last.items() if k.startswith("w_") and v not in ("", None)}
    shares = {k[6:]: float(v) for k, v in last.items() if k.startswith("share_") and v not in ("", None)}
    return [_decomposition_line(f"at step {last['step']}", weights, shares, float(last["decomp_r2"]))]


def _why(evidence: dict[str, Any]) -> str:
    """What made an intervention happen, in words: the returns' structural evidence, the monitor's
    anomaly with its strongest readings, or a periodic review (the no-MCM ablation)."""
    att = evidence.get("return_attribution") or {}
    gains = att.get("feature_gains") or []
    if evidence.get("cause") == "structural" and gains:
        top = gains[0]
        shape = top["feature"] if top["form"] == "value" else f"-{top['feature']}²"
        return (f"the returns show a structural flaw: the program's factors explain the episodic returns out of "
                f"sample with R² {att['program_cv_r2']:.2f}, with {shape} added {top['cv_r2']:.2f} "
                f"({top['gain']:+.2f})")
    plateau = evidence.get("plateau")
    if evidence.get("cause") == "plateau" and plateau:
        return (f"learning had stalled: the held-out return's median {plateau['recent_median']:.6g} against "
                f"{plateau['previous_median']:.6g} before ({100 * plateau['rise']:+.1f}%), the episodes settled at "
                f"{plateau['feature']} = {plateau['center']:.4g} ± {plateau['halfwidth']:.3g}")
    if evidence.get("cause", "anomaly") == "anomaly" and evidence.get("guided", True) \
            and evidence.get("contributors"):
        why = "; ".join(f"{c['reading']} ({str(c['metric']).upper()} = {c['value']:.2f})"
                        for c in evidence["contributors"])
        return f"the monitor flagged a persistent anomaly (S = {_fmt(evidence.get('score'))}): {why}"
    return "periodic review without diagnostic evidence (no-MCM ablation)"


def _plateau_lines(run: Path) -> list[str]:
    """The plateau detector's reports and each escape's probation (``plateau.csv``)."""
    rows = read_csv(run / "plateau.csv")
    lines = []
    for r in rows:
        if r["event"] == "too_late":
            lines.append(f"No escape at step {r['step']}: its probation would have outlasted the run.")
            continue
        rise = 100 * float(r["rise"])
        if r["event"] == "plateau":
            lines.append(f"Plateau at step {r['step']}: held-out return {float(r['median']):.6g} against "
                         f"{float(r['before']):.6g} ({rise:+.1f}%), episodes settled at {r['feature']} = "
                         f"{float(r['center']):.4g} ± {float(r['halfwidth']):.3g}.")
        else:
            kept = r["event"] == "escape_kept"
            lines.append(f"Escape judged at step {r['step']}: held-out return {float(r['median']):.6g} against the "
                         f"plateau's {float(r['before']):.6g} ({rise:+.1f}%): "
                         + ("kept." if kept else f"rolled back (program v{r['version']})."))
    return lines


def _factor_codes(path: Path) -> dict[str, str]:
    """name → code of a stored program version's factors (empty if unreadable)."""
    data = _load(path) or {}
    factors = data.get("factors") if isinstance(data, dict) else None
    return {str(f.get("name")): str(f.get("code", "")) for f in factors or [] if isinstance(f, dict)}


@dataclass(frozen=True)
class Intervention:
    """One intervention of a run, as a report lists it: when, why, what it installed, and what the
    evaluation return did around it (the mean of the evaluations within three intervals before and after)."""

    folder: str
    step: int
    why: str
    accepted: bool
    operators: tuple[str, ...]
    version: int | None
    added: tuple[str, ...]
    removed: tuple[str, ...]
    changed: tuple[str, ...]
    reason: str
    return_before: float | None
    return_after: float | None

    @property
    def edit(self) -> str:
        """The installed edit in a few words (``Add: +r_x_velocity``; ``~`` marks a factor whose code changed),
        or ``-`` when nothing was installed."""
        if not self.accepted:
            return "-"
        names = ", ".join([*(f"+{n}" for n in self.added), *(f"−{n}" for n in self.removed),
                           *(f"~{n}" for n in self.changed)])
        return "+".join(self.operators) + (f": {names}" if names else "")


@dataclass(frozen=True)
class Diagnosis:
    """The structural check's verdict over a run (``diagnostics.csv``'s ``structural_flaw``): on how many
    cycles it called the program flawed, and at the first, which task feature would have explained the
    episodic returns and by how much. An ablation without SRR records it and never acts on it."""

    first_step: int
    cycles: int
    feature: str
    r2: float
    r2_with: float


def structural_diagnosis(run_dir: str | Path, rows: list[dict[str, str]] | None = None) -> Diagnosis | None:
    """The run's structural diagnosis, or None if the check never called its program flawed (or the run
    predates the column); ``rows`` are its ``diagnostics.csv`` rows if the caller has read them already."""
    if rows is None:
        rows = read_csv(Path(run_dir) / "diagnostics.csv")
    flagged = [r for r in rows if r.get("structural_flaw") == "1"]
    if not flagged:
        return None
    first = flagged[0]
    r2 = float(first["returns_cv_r2"])
    return Diagnosis(int(first["step"]), len(flagged), first["unexplained"], r2,
                     r2 + float(first["unexplained_gain"]))


def interventions(run_dir: str | Path) -> list[Intervention]:
    """Every intervention recorded under ``run_dir/interventions``, in order (unreadable ones skipped)."""
    run = Path(run_dir)
    cfg = ((_load(run / "config.json") or {}).get("config") or {})
    every = int(cfg.get("eval_every", 5000))
    evals = read_csv(run / "eval.csv")
    out = []
    for path in sorted((run / "interventions").glob("*/decision.json")):
        decision = _load(path)
        evidence = _load(path.parent / "evidence.json")
        if not isinstance(decision, dict) or not isinstance(evidence, dict):
            continue
        step = int(evidence.get("step", decision.get("step", 0)) or 0)
        version = decision.get("version")
        accepted = bool(decision.get("accepted"))
        added: tuple[str, ...] = ()
        removed: tuple[str, ...] = ()
        changed: tuple[str, ...] = ()
        if accepted and isinstance(version, int) and version > 0:
            new = _factor_codes(run / "programs" / f"v{version:03d}.json")
            old = _factor_codes(run / "programs" / f"v{version - 1:03d}.json")
            added = tuple(n for n in new if n not in old)
            removed = tuple(n for n in old if n not in new)
            changed = tuple(n for n in new if n in old and new[n] != old[n])
        out.append(Intervention(
            path.parent.name, step, _why(evidence), accepted, tuple(decision.get("operators") or ()),
            version if isinstance(version, int) else None, added, removed, changed, str(decision.get("reason", "")),
            _mean_return(evals, step - 3 * every, step), _mean_return(evals, step, step + 3 * every)))
    return out


def _program_origin(run: Path, cfg: dict[str, Any]) -> str:
    """Who wrote program v0, from ``programs/origin.json`` (or, for older runs, the configuration)."""
    offline = "the offline rule-based reward engineer (not an LLM)"
    origin = _load(run / "programs" / "origin.json")
    if not origin:
        if cfg.get("program"):
            return f"was read from {cfg['program']}"
        engineer = cfg.get("llm", {}).get("backend", "offline")
        return f"was written by {offline if engineer == 'offline' else engineer}"
    attempts = origin.get("attempts") or []
    if origin.get("written_by") == "file":
        return f"was read from {origin.get('file')}"
    if origin.get("fallback_from"):
        return (f"was written by {offline}, because every reply of {origin['fallback_from']} was refused "
                f"({_count(len(attempts), 'attempt')}; {origin.get('reason')})")
    who = offline if origin.get("written_by") == "offline" else origin.get("written_by")
    turns = ("" if len(attempts) <= 1 else
             f", admitted on attempt {len(attempts)} (the earlier replies were sent back with their errors)")
    return f"was written by {who}{turns}"


def explain(run_dir: str | Path) -> str:
    run = Path(run_dir)
    cfg_file = _load(run / "config.json")
    if cfg_file is None:
        raise UsageError(f"explain {run}: not a run directory (no readable config.json)")
    cfg = cfg_file["config"]
    status = _load(run / "status.json") or {}
    evals = read_csv(run / "eval.csv")
    lines = [
        f"Run {run}: method {cfg['method']} on {cfg['task']} with {cfg['algo'].upper()}, seed {cfg['seed']}, "
        f"{cfg['steps']} steps; status {describe_status(status)}.",
        f"Method: {(cfg_file.get('method') or {}).get('description', cfg['method'])}",
    ]
    env = cfg_file.get("environment") or {}
    if env.get("cpu"):
        # A seed reproduces the run exactly only on this kind of CPU and software (see README).
        lines.append(f"Machine: {env['cpu']} ({env.get('cpu_capability', '?')}), torch {env.get('torch', '?')}, "
                     f"GEMM backend {env.get('gemm_backend', '?')}.")
    if env.get("source"):
        commit, _, digest = str(env["source"]).partition("+")
        lines.append(f"Code: mira {env.get('mira', '?')} at commit {commit[:12]}"
                     + (f", with uncommitted changes to src (diff digest {digest})." if digest else "."))
    if fork := cfg_file.get("forked_from"):
        installed = (f"; installed program {fork['program_file']} at the fork"
                     if fork.get("program_file") else "")
        installed += "".join(f"; --set {a}" for a in fork.get("settings") or [])
        lines.append(f"Forked from {fork.get('run')} at step {fork.get('step')} (its method {fork.get('method')}, "
                     f"seed {fork.get('seed')}; checkpoint SHA-256 {str(fork.get('sha256'))[:12]}){installed}: its "
                     "record before the step is the parent's.")
    for resumed in cfg_file.get("resumed_elsewhere") or []:
        lines.append(f"Resumed from step {resumed.get('step')} on another machine, software or source: "
                     + "; ".join(str(d) for d in resumed.get("drift") or []) + ".")
    if evals:
        last = evals[-1]
        best = max(evals, key=lambda r: float(r["return_mean"]))
        lines.append(f"Evaluation: {len(evals)} evaluations; last return {float(last['return_mean']):.1f} at step "
                     f"{last['step']}; best {float(best['return_mean']):.1f} at step {best['step']}.")
    programs = sorted((run / "programs").glob("v*.json"))
    if programs:
        v0 = _load(programs[0]) or {}
        names = ", ".join(f"{f['name']} ({f['type']})" for f in v0.get("factors", []))
        lines.append(f"Program v0 {_program_origin(run, cfg)}: {names}.")
        if len(programs) > 1:
            versions = ", ".join(p.stem.lstrip("v").lstrip("0") or "0" for p in programs)
            lines.append(f"The run ended on program v{int(programs[-1].stem[1:])} (versions: {versions}).")
    lines += _decomposition(run)
    diag = read_csv(run / "diagnostics.csv")
    if diag:
        triggers = [r for r in diag if r.get("trigger") == "1"]
        lines.append(f"Monitor: {_count(len(diag), 'cycle')}, {_count(len(triggers), 'anomaly trigger')}"
                     + (f" (at step{'s' if len(triggers) > 1 else ''} {', '.join(r['step'] for r in triggers)})."
                        if triggers else "."))
        measured = [r for r in diag if r.get("returns_cv_r2")]
        if measured:
            last = measured[-1]
            lines.append(f"Return attribution at step {last['step']}: the program's factors explain the episodic "
                         f"returns out of sample with R² {float(last['returns_cv_r2']):.2f}"
                         + (f"; the most a task feature adds is {float(last['unexplained_gain']):+.2f} "
                            f"({last['unexplained']})." if last.get("unexplained") else "."))
        found = structural_diagnosis(run, diag)
        if found is not None:
            lines.append(f"Structural check: the returns called the program flawed on {_count(found.cycles, 'cycle')}, "
                         f"first at step {found.first_step} (with {found.feature} its factors would explain them "
                         f"with R² {found.r2_with:.2f} instead of {found.r2:.2f})"
                         + ("; this method has no SRR, so the diagnosis was logged and nothing was installed."
                            if cfg.get("method") == "mira-no-srr" else "."))
    lines += _plateau_lines(run)
    interventions = sorted((run / "interventions").glob("*/decision.json"))
    if not interventions and (run / "interventions").exists():
        lines.append("No intervention was made.")
    for path in interventions:
        folder = path.parent
        decision = _load(path) or {}
        evidence = _load(folder / "evidence.json") or {}
        step = int(evidence.get("step", 0))
        lines.append("")
        lines.append(f"Intervention {folder.name} at step {step}:")
        lines.append(f"  why: {_why(evidence)}.")
        hyps = evidence.get("hypotheses") or []
        if hyps:
            lines.append("  hypotheses: " + ", ".join(f"{h['operator']} ({h['because']})" for h in hyps[:3]))
        attempts = _load(folder / "attempts.json") or []
        if len(attempts) > 1:
            refused = [a for a in attempts if not a.get("admitted")]
            first = "; ".join(refused[0].get("errors", [])[:2]) if refused else ""
            replies = "reply" if len(refused) == 1 else "replies"
            lines.append(f"  the engineer answered {_count(len(attempts), 'time')}: {len(refused)} {replies} sent back "
                         "with the checker's errors" + (f" (first: {first})" if first else ""))
        candidates = _load(folder / "candidates.json") or []
        for c in candidates:
            verdicts = c.get("verdicts", {})
            eff = verdicts.get("efficacy")
            ops = "+".join(c.get("operators", [])) or "?"
            if eff:
                figures = (f"AUC {eff['auc']:.3f} (p {eff['auc_p']:.3g}), Spearman {eff['spearman']:.2f}, "
                           f"J_SRR {eff['j_srr']:.3f}")
            else:
                figures = "not measured"
            returns = verdicts.get("returns")
            if returns:
                figures += f", return R² {returns['cv_r2']:.2f} ({returns['gain']:+.2f})"
            if verdicts.get("shaping"):
                figures = "shaping term (outside the fitted reward): bounded on the held-out states"
            verdict = verdicts.get("rejected") or "passed"
            lines.append(f"  candidate {c['index']} [{ops}]: {figures}; {verdict}")
        if decision.get("accepted"):
            lines.append(f"  decision: accepted -> program v{decision.get('version')} ({decision.get('reason')}).")
            diff = folder / "accepted.diff"
            if diff.is_file():
                changed = [ln for ln in diff.read_text().splitlines()
                           if ln.startswith(("+", "-")) and not ln.startswith(("+++", "---"))]
                lines += ["    " + ln for ln in changed[:12]]
            before = _mean_return(evals, step - 3 * int(cfg.get("eval_every", 5000)), step)
            after = _mean_return(evals, step, step + 3 * int(cfg.get("eval_every", 5000)))
            lines.append(f"  return: {_fmt(before)} in the evaluations before, {_fmt(after)} in those after.")
        else:
            kind = "failed" if decision.get("failed") else "abstained (backoff)"
            lines.append(f"  decision: {kind}: {decision.get('reason')}")
    return "\n".join(lines)
