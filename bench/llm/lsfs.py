"""LSFS with a recorded LLM: every built-in task card's initial program, asked of one backend.

Each card's exchange goes to ``OUT/<task>/llm/exchanges.jsonl`` (the audit log a run keeps, replayable
with ``mira llm export``), the admitted program to ``OUT/<task>/program.json``, and a line per card to
``OUT/lsfs.json``: admitted or not, on which attempt, the errors of each refused attempt, the checks'
warnings. With ``--llm script:FILE`` (an export) it replays a recording without any endpoint.

    python bench/llm/lsfs.py --llm openai:MODEL --base-url http://127.0.0.1:8765/v1 --out bench/llm/lsfs
    python bench/llm/lsfs.py --replay bench/llm/lsfs            # each card's recorded replies, offline
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mira.engineer.backends import make_backend
from mira.engineer.lsfs import SynthesisError, synthesize_program
from mira.factors.program import save_program
from mira.llm.config import LLMConfig
from mira.tasks.card import builtin_task_names, load_task
from mira.tasks.envs import action_dim


def run_card(task: str, spec: str, base_url: str | None, out: Path, followups: int) -> dict[str, object]:
    card = load_task(task)
    folder = out / task
    backend = make_backend(spec, base_url=base_url, audit_dir=folder, timeout_s=3600, max_retries=0)
    try:
        made = synthesize_program(card, backend, action_dim(card), followups=followups)
    except SynthesisError as exc:
        return {"task": task, "admitted": False, "attempts": [a.as_dict() for a in exc.attempts], "error": str(exc)}
    save_program(made.program, folder / "program.json")
    return {"task": task, "admitted": True, "attempt": len(made.attempts),
            "attempts": [a.as_dict() for a in made.attempts], "warnings": made.warnings,
            "factors": [f.name for f in made.program.factors]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--llm", default=None, help="backend spec (openai:MODEL, script:FILE)")
    p.add_argument("--base-url", default=None)
    p.add_argument("--out", type=Path, default=Path("bench/llm/lsfs"))
    p.add_argument("--tasks", default=",".join(builtin_task_names()))
    p.add_argument("--followups", type=int, default=LLMConfig.followups)
    p.add_argument("--replay", type=Path, default=None,
                   help="a recorded folder: replay each card's exchanges (exported as a script) offline")
    args = p.parse_args(argv)
    rows = []
    for task in args.tasks.split(","):
        if args.replay is not None:
            from mira.llm.export import export_run

            script = args.out / "replay" / f"{task}.jsonl"
            export_run(args.replay / task, out=script, fmt="script")
            row = run_card(task, f"script:{script}", None, args.out / "replay", args.followups)
        else:
            row = run_card(task, args.llm, args.base_url, args.out, args.followups)
        print(json.dumps(row), flush=True)
        rows.append(row)
    target = (args.out / "replay" if args.replay is not None else args.out) / "lsfs.json"
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps(rows, indent=1) + "\n")
    admitted = sum(bool(r["admitted"]) for r in rows)
    first = sum(r.get("attempt") == 1 for r in rows)
    print(f"{admitted} of {len(rows)} cards admitted, {first} on the first attempt", file=sys.stderr)
    return 0 if admitted == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
