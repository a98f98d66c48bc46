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
"""

from __future__ import annotations

import argparse
import json
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


def evidence() -> Evidence:
    d = {"peg": -1.8, "tpd": 0.1, "pvc": 0.2, "fap": 0.0, "rpe": 2.4}
    plateau = {"step": 60_000, "recent_median": 130_000.0, "previous_median": 129_500.0, "rise": 0.004,
               "feature": "torso_height", "center": 0.40, "halfwidth": 0.01, "visited": [0.10, 0.45],
               "d_peg": -1.8, "d_rpe": 2.4, "reward_per_step": 130.0}
    return Evidence(step=60_000, d=d, d_raw=d, score=None, threshold=None, gradient={}, contributors=[],
                    recent_return=130_000.0, baseline_return=129_000.0,
                    stagnation_band={"feature": "torso_height", "center": 0.40, "halfwidth": 0.01},
                    attention={}, cause="plateau", plateau=plateau)


def write_prompt(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    card = load_task(TASK, check_env=False)
    request = build_srr_request(card, example_program(TASK, 0), evidence(), [], MAX_CANDIDATES, OPERATORS,
                                ACTION_DIM)
    system, user = (m["content"] for m in request.messages)
    (out / "prompt.txt").write_text(f"SYSTEM:\n{system}\n\nUSER:\n{user}")
    (out / "request.json").write_text(json.dumps(request.to_dict(), indent=1))
    print(f"wrote {out / 'prompt.txt'}")


def check(reply: Path, out: Path) -> list[dict[str, object]]:
    out.mkdir(parents=True, exist_ok=True)
    card = load_task(TASK)
    obs, actions = collect_states(card, 300, seed=4)
    script = out / "replies.jsonl"
    script.write_text(json.dumps({"content": reply.read_text()}) + "\n")
    backend = make_backend(f"script:{script}", audit_dir=out)

    def proxy(program: FactorProgram, states: np.ndarray) -> np.ndarray:  # not reported: see the docstring
        return np.zeros(len(states))

    Reframer(SRRConfig(), card, backend, action_dim=ACTION_DIM, permutations=100).reframe(
        out / "intervention", example_program(TASK, 0), evidence(), obs, np.zeros(len(obs)), obs, actions, proxy,
        seed=0)
    rows = []
    for c in json.loads((out / "intervention" / "candidates.json").read_text()):
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
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("prompt")
    p.add_argument("--out", type=Path, required=True)
    c = sub.add_parser("check")
    c.add_argument("reply", type=Path)
    c.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.command == "prompt":
        write_prompt(args.out)
    else:
        check(args.reply, args.out)


if __name__ == "__main__":
    main()
