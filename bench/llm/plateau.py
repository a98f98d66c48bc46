"""A plateau's SRR prompt, and a recorded reply to it judged by SRR's own gates.

The prompt is the one a HumanoidStandup run sends when the plateau detector reports a crouch (the
figures of a sitting SAC policy at 100k-200k steps: return about 130,000, torso height 0.40 ± 0.01 over
a visited [0.10, 0.45]); it is built by the same code as in a run (``build_srr_request``). ``check``
passes a reply through the parser, the static checker, the sandbox (on states of random-action
episodes from reset, where a humanoid lies: the states of a run's replay buffer are not at hand here)
and, for a candidate that changes only SHAPE factors, the shaping checks. It reports admission and
those verdicts only: the proxy-efficacy and returns tests need a run's held-out states and episodes.

    python bench/llm/plateau.py prompt --out bench/llm/plateau
    python bench/llm/plateau.py check bench/llm/plateau/reply-1.txt --out /tmp/plateau-check

With ``--run RUN --step STEP`` the prompt is a run's own at a checkpoint: the program in force there, the
plateau report of its held-out episodes as the detector builds it (``bench/fork_escape.py``), the
monitor's diagnostics of that cycle (``diagnostics.csv``), the decomposition head's fit
(``decomposition.json``, when written at that step) and the return's medians over the last ten
evaluations against the ten before. ``check --run RUN --step STEP --program-out FILE`` then writes the
first candidate SRR would install on a plateau (admitted, only SHAPE factors changed, the shaping
checks passed) as a program for ``mira train --fork ... --fork-program FILE``: the LLM's escape, measured
against the offline engineer's in paired forks.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from mira.engineer.backends import make_backend
from mira.engineer.srr_prompt import Evidence, build_srr_request
from mira.factors import example_program
from mira.factors.program import FactorProgram
from mira.factors.sandbox import collect_states
from mira.srr.config import SRRConfig
from mira.srr.hypotheses import OPERATORS
from mira.srr.reframe import Reframer
from mira.tasks import load_task

TASK, ACTION_DIM, MAX_CANDIDATES = "humanoidstandup", 17, 3
METRICS = ("peg", "tpd", "pvc", "fap", "rpe")


def evidence() -> Evidence:
    d = {"peg": -1.8, "tpd": 0.1, "pvc": 0.2, "fap": 0.0, "rpe": 2.4}
    plateau = {"step": 60_000, "recent_median": 130_000.0, "previous_median": 129_500.0, "rise": 0.004,
               "feature": "torso_height", "center": 0.40, "halfwidth": 0.01, "visited": [0.10, 0.45],
               "d_peg": -1.8, "d_rpe": 2.4, "reward_per_step": 130.0}
    return Evidence(step=60_000, d=d, d_raw=d, score=None, threshold=None, gradient={}, contributors=[],
                    recent_return=130_000.0, baseline_return=129_000.0,
                    stagnation_band={"feature": "torso_height", "center": 0.40, "halfwidth": 0.01},
                    attention={}, cause="plateau", plateau=plateau)


def run_evidence(run: Path, step: int) -> tuple[Evidence, FactorProgram]:
    """The evidence a run's plateau at checkpoint ``step`` would carry, and the program in force there."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from fork_escape import plateau_report  # bench/: the report as the detector builds it

    report, program = plateau_report(run, step)
    with (run / "diagnostics.csv").open(encoding="utf-8") as f:
        row = next((r for r in csv.DictReader(f) if int(r["step"]) == step), None)
    if row is None:
        raise SystemExit(f"{run}: diagnostics.csv has no cycle at step {step}")
    with (run / "eval.csv").open(encoding="utf-8") as f:
        evals = [float(r["return_mean"]) for r in csv.DictReader(f) if int(r["step"]) <= step]
    if len(evals) < 20:
        raise SystemExit(f"{run}: fewer than 20 evaluations up to step {step}")
    recent, before = float(np.median(evals[-10:])), float(np.median(evals[-20:-10]))
    d = {m: float(row[f"d_{m}"]) for m in METRICS}
    saved = run / "decomposition.json"
    fit = json.loads(saved.read_text(encoding="utf-8")) if saved.is_file() else {}
    decomposition = {k: v for k, v in fit.items() if k not in ("step", "version")} if fit.get("step") == step else None
    band = {"feature": report["feature"], "center": report["center"], "halfwidth": report["halfwidth"]}
    plateau = {"step": step, "recent_median": recent, "previous_median": before, "rise": (recent - before) / before,
               **band, "visited": report["visited"], "start": report["start"], "d_peg": d["peg"],
               "d_rpe": d["rpe"], "reward_per_step": report["reward_per_step"]}
    score = float(row["score"]) if row.get("score") else None
    threshold = float(row["threshold"]) if row.get("threshold") else None
    evidence = Evidence(step=step, d=d, d_raw={m: float(row[f"raw_{m}"]) for m in METRICS}, score=score,
                        threshold=threshold, gradient={}, contributors=[], recent_return=report["held_out_return"],
                        baseline_return=float(row["baseline"]), stagnation_band=band, attention={},
                        decomposition=decomposition, cause="plateau", plateau=plateau)
    return evidence, program


def evidence_and_program(run: Path | None, step: int | None) -> tuple[Evidence, FactorProgram]:
    """A run's plateau at ``step`` (:func:`run_evidence`), or the fixed figures and the task's own program."""
    if run is not None and step is not None:
        return run_evidence(run, step)
    return evidence(), example_program(TASK, 0)


def write_prompt(out: Path, run: Path | None = None, step: int | None = None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    card = load_task(TASK, check_env=False)
    ev, program = evidence_and_program(run, step)
    request = build_srr_request(card, program, ev, [], MAX_CANDIDATES, OPERATORS, ACTION_DIM)
    system, user = (m["content"] for m in request.messages)
    (out / "prompt.txt").write_text(f"SYSTEM:\n{system}\n\nUSER:\n{user}")
    (out / "request.json").write_text(json.dumps(request.to_dict(), indent=1))
    print(f"wrote {out / 'prompt.txt'}")


def check(reply: Path, out: Path, run: Path | None = None, step: int | None = None,
          program_out: Path | None = None) -> list[dict[str, object]]:
    out.mkdir(parents=True, exist_ok=True)
    card = load_task(TASK)
    ev, program = evidence_and_program(run, step)
    obs, actions = collect_states(card, 300, seed=4)
    script = out / "replies.jsonl"
    script.write_text(json.dumps({"content": reply.read_text()}) + "\n")
    backend = make_backend(f"script:{script}", audit_dir=out)

    def proxy(program: FactorProgram, states: np.ndarray) -> np.ndarray:  # not reported: see the docstring
        return np.zeros(len(states))

    Reframer(SRRConfig(), card, backend, action_dim=ACTION_DIM, permutations=100).reframe(
        out / "intervention", program, ev, obs, np.zeros(len(obs)), obs, actions, proxy, seed=0)
    rows = []
    candidates = json.loads((out / "intervention" / "candidates.json").read_text())
    for c in candidates:
        verdicts = c.get("verdicts", {})
        sandbox = verdicts.get("sandbox", {})
        shape_only = "shaping" in verdicts
        admitted = bool(sandbox.get("ok")) and not c.get("parse_error")
        # What refused it before efficacy, or the shaping checks' verdict; efficacy itself is not measured here.
        refused = c.get("parse_error") or verdicts.get("rejected") if not admitted or shape_only else None
        rows.append({"candidate": c["index"], "operators": c.get("operators"), "admitted": admitted,
                     "refused": refused, "shape_only": shape_only,
                     "shaping_passed": verdicts["shaping"]["passed"] if shape_only else None,
                     "shaping_problems": verdicts["shaping"]["problems"] if shape_only else None,
                     "sandbox_warnings": {n: f.get("warnings") for n, f in sandbox.get("factors", {}).items()
                                          if f.get("warnings")}})
    (out / "verdicts.json").write_text(json.dumps(rows, indent=1))
    for r in rows:
        print(json.dumps(r))
    if program_out is not None:
        chosen = next((r for r in rows if r["admitted"] and r["shape_only"] and r["shaping_passed"]), None)
        if chosen is None:
            raise SystemExit(f"{reply}: no candidate SRR would install on a plateau (admitted, SHAPE-only, shaping "
                             "checks passed): no program written")
        built = next(c for c in candidates if c["index"] == chosen["candidate"])["program"]
        written = {**built, "version": 0, "parent_version": None, "edits": [],
                   "diff": "", "rationale": f"candidate {chosen['candidate']} of {reply.name} (an LLM's reply to "
                                            f"the plateau prompt of {run} at step {step})"}
        program_out.write_text(json.dumps(written, indent=2) + "\n", encoding="utf-8")
        print(f"wrote candidate {chosen['candidate']} to {program_out}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("prompt")
    p.add_argument("--out", type=Path, required=True)
    c = sub.add_parser("check")
    c.add_argument("reply", type=Path)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--program-out", type=Path, help="with --run: write the candidate SRR would install here")
    for q in (p, c):
        q.add_argument("--run", type=Path, help="a run directory: its own plateau at --step, not the fixed figures")
        q.add_argument("--step", type=int, help="with --run: the checkpoint whose plateau is asked about")
    args = parser.parse_args()
    if (args.run is None) != (args.step is None):
        parser.error("--run and --step go together")
    if args.command == "prompt":
        write_prompt(args.out, args.run, args.step)
    else:
        check(args.reply, args.out, args.run, args.step, args.program_out)


if __name__ == "__main__":
    main()
