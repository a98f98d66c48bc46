"""Replay a recorded LLM run offline and check that it reproduces: the run's exchanges become a response
cache (``mira llm export --format cache``), the same ``mira train`` command runs again with
``--llm-offline-only`` (a request not in the cache is an error, never a call), and the replay's
evaluations are compared with the recording's, step by step.

    python bench/llm/replay.py bench/runs/llm_hc/halfcheetah/no_progress/mira-sac-s0 --steps 20000

The same machine and code reproduce a run bit for bit (float rounding differs between CPU models).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from mira.llm.export import export_run


def replay(run: Path, steps: int, out: Path) -> tuple[int, int]:
    """Rerun ``run`` to ``steps`` from its exchanges alone; (evaluations compared, evaluations equal)."""
    config = json.loads((run / "config.json").read_text())["config"]
    cache = out / "cache"
    export_run(run, out=cache, fmt="cache")
    cmd = [sys.executable, "-m", "mira.cli", "train", "--task", config["task"], "--method", config["method"],
           "--algo", config["algo"], "--seed", str(config["seed"]), "--steps", str(steps), "--threads", "1",
           "--eval-every", str(config["eval_every"]), "--eval-episodes", str(config["eval_episodes"]),
           "--llm", config["llm"]["backend"], "--llm-cache", str(cache), "--llm-offline-only", "--quiet",
           "--out", str(out / "run"), "--overwrite"]
    if config.get("program"):
        cmd += ["--program", config["program"]]
    for key in ("timeout_s", "max_retries"):
        cmd += ["--set", f"llm.{key}={config['llm'][key]}"]
    # An offline replay sends nothing: the endpoint's key is not needed, but the client wants one.
    env = {"OPENAI_API_KEY": "unused", **os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run(cmd, check=True, env=env)
    recorded = {r["step"]: r["return_mean"] for r in csv.DictReader((run / "eval.csv").open())}
    replayed = {r["step"]: r["return_mean"] for r in csv.DictReader((out / "run" / "eval.csv").open())}
    common = [s for s in replayed if s in recorded]
    return len(common), sum(recorded[s] == replayed[s] for s in common)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--steps", type=int, default=20_000)
    args = p.parse_args(argv)
    ok = True
    for run in args.runs:
        with tempfile.TemporaryDirectory() as tmp:
            compared, equal = replay(run, args.steps, Path(tmp))
        print(f"{run}: {equal} of {compared} evaluations to step {args.steps} replayed bit for bit")
        ok = ok and compared > 0 and equal == compared
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
