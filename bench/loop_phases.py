"""Where a whole training step goes, per phase, in the real trainer:

    python bench/loop_phases.py                           # sparse and hars, SAC, HalfCheetah, 1 thread
    python bench/loop_phases.py --methods sparse,hars,mira --algo ddpg --steps 6000
    python bench/loop_phases.py --methods hars --one-batch-at-a-time   # HARS shaping batch by batch
    python bench/loop_phases.py --set hars.update_every=16            # any configuration override
    python bench/loop_phases.py --methods sparse,hars,hars+hars.update_every=1   # A/B

Each method runs ``mira train`` in a fresh subprocess (learning starts at ``--learning-starts``; no
evaluation or checkpoint inside the run) with thin timers around the agent's ``update`` and ``act``,
the environment's ``step``, the buffer's ``sample`` and ``add`` and every reward-source hook
(``relabel``, ``relabel_many``, ``update``, ``on_transition``). Printed: each phase's
total and its time per update, the wall time per update of the whole loop and, for a source that
trains on every k-th update (HARS), the agent's update time by position in that cycle (how much the
source's work slows the agent's next updates through the caches). Methods are run alternately,
``--repeats`` times, so that a machine whose speed drifts hits all of them alike.

A method written ``NAME+KEY=VALUE[+KEY=VALUE...]`` runs NAME with those overrides on top of ``--set``
(so two settings of one method can be compared in the same alternation). ``--threads`` sets the
intra-op threads of every run (1 by default).

``--one-batch-at-a-time`` makes reward sources report a lookahead of 1, i.e. every batch is sampled
and relabelled right before its update (how the trainer worked before grouped shaping), for A/B runs.
Nested phases overlap (``relabel_many`` contains ``relabel``). This is a
measurement script, not a test.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

PHASES = {
    "agent": ("update", "act"),
    "env": ("step",),
    "buffer": ("sample", "add"),
    "reward": ("relabel", "relabel_many", "update", "on_transition"),
}


def _worker(args: argparse.Namespace) -> dict[str, Any]:
    import mira.loop.trainer as trainer_mod
    from mira.cli import main as cli_main
    from mira.rewards.base import RewardSource

    if args.one_batch_at_a_time:
        from mira.shaping.source import HarsReward

        for cls in (RewardSource, HarsReward):  # HarsReward is the one source that overrides it
            setattr(cls, "lookahead", lambda self: 1)  # noqa: B010
    total: dict[str, float] = collections.defaultdict(float)
    calls: collections.Counter[str] = collections.Counter()
    marks: dict[str, float] = {}
    frozen: dict[str, Any] = {}
    by_position: dict[int, list[float]] = collections.defaultdict(list)
    original_run = trainer_mod.Trainer.run

    def timed(label: str, fn: Any) -> Any:
        @functools.wraps(fn)
        def wrapper(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                total[label] += time.perf_counter() - t0
                calls[label] += 1

        return wrapper

    def run(self: Any) -> Any:
        objects = {"agent": self.agent, "env": self.env, "buffer": self.buffer, "reward": self.reward}
        for owner, names in PHASES.items():
            for name in names:
                if hasattr(objects[owner], name):
                    setattr(objects[owner], name, timed(f"{owner}.{name}", getattr(objects[owner], name)))
        update = self.agent.update

        # A source that trains on every k-th update (HARS) counts its updates in ``calls``.
        cycle = getattr(getattr(self.reward, "config", None), "update_every", None) \
            if hasattr(self.reward, "calls") else None

        def first_and_last(batch: Any, reward: Any) -> Any:
            if self.step == args.learning_starts + 1:
                marks["t0"] = time.perf_counter()
                total.clear()
                calls.clear()
                by_position.clear()
            # Where the agent's update falls in the reward source's training cycle (HARS: 0 = the
            # update whose batch HARS trains on, 1 = the first after its grouped shaping pass).
            position = self.reward.calls % cycle if cycle else 0
            t0 = time.perf_counter()
            out = update(batch, reward)
            by_position[position].append(time.perf_counter() - t0)
            if self.step == args.steps:  # the final evaluation falls outside
                marks["t1"] = time.perf_counter()
                frozen.update(total=dict(total), calls=dict(calls))
            return out

        self.agent.update = first_and_last
        return original_run(self)

    trainer_mod.Trainer.run = run  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory(prefix="mira-phases-") as tmp:
        cli_main(["train", "--task", args.task, "--method", args.method, "--algo", args.algo,
                  "--steps", str(args.steps), "--learning-starts", str(args.learning_starts),
                  "--eval-every", str(10 * args.steps), "--checkpoint-every", str(10 * args.steps),
                  "--threads", str(args.threads), "--seed", str(args.seed), "--quiet", "--out", str(Path(tmp) / "run"),
                  *(x for kv in args.set for x in ("--set", kv))])
    updates = args.steps - args.learning_starts
    return {"wall_ms_per_update": 1e3 * (marks["t1"] - marks["t0"]) / updates,
            "phases_ms_per_update": {k: 1e3 * v / updates for k, v in frozen["total"].items()},
            "calls": frozen["calls"],
            "agent_update_ms_by_position": {str(k): 1e3 * statistics.fmean(v) for k, v in sorted(by_position.items())}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", default="sparse,hars")
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--algo", default="sac", choices=("sac", "ddpg"))
    p.add_argument("--steps", type=int, default=4000)
    p.add_argument("--learning-starts", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--one-batch-at-a-time", action="store_true")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="configuration override passed to every run, e.g. hars.update_every=16")
    p.add_argument("--worker", metavar="METHOD", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        args.method = args.worker
        print(json.dumps(_worker(args)))
        return
    results: dict[str, list[dict[str, Any]]] = collections.defaultdict(list)
    for repeat in range(args.repeats):
        for method in args.methods.split(","):
            # "+" starts an override only where a KEY= follows, so values such as 1e+3 stay whole.
            name, *overrides = re.split(r"\+(?=[A-Za-z_][\w.]*=)", method)
            cmd = [sys.executable, __file__, "--worker", name, "--task", args.task, "--algo", args.algo,
                   "--steps", str(args.steps), "--learning-starts", str(args.learning_starts),
                   "--seed", str(args.seed), "--threads", str(args.threads)] + \
                  (["--one-batch-at-a-time"] if args.one_batch_at_a_time else []) + \
                  [x for kv in [*args.set, *overrides] for x in ("--set", kv)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            results[method].append(res)
            print(f"[{repeat + 1}/{args.repeats}] {method:12s} {res['wall_ms_per_update']:.3f} ms per update",
                  flush=True)
    base = results.get("sparse")
    for method, runs in results.items():
        wall = statistics.median(r["wall_ms_per_update"] for r in runs)
        extra = ""
        if base and method != "sparse":
            ratios = [r["wall_ms_per_update"] / b["wall_ms_per_update"] for r, b in zip(runs, base, strict=False)]
            extra = f"  ({100 * (statistics.median(ratios) - 1):+.1f}% over sparse, per repeat: " + \
                ", ".join(f"{100 * (x - 1):+.1f}%" for x in ratios) + ")"
        print(f"\n{method}: {wall:.3f} ms per update (median of {len(runs)}){extra}")
        keys = sorted(runs[0]["phases_ms_per_update"], key=lambda k: -runs[0]["phases_ms_per_update"][k])
        for k in keys:
            vals = [r["phases_ms_per_update"].get(k, 0.0) for r in runs]
            print(f"  {k:28s} {statistics.median(vals):7.3f} ms per update   ({runs[0]['calls'].get(k, 0)} calls)")
        positions = runs[0]["agent_update_ms_by_position"]
        if len(positions) > 1:
            print("  agent.update by position in the source's training cycle (ms, per repeat): " + "; ".join(
                f"{p}: " + "/".join(f"{r['agent_update_ms_by_position'][p]:.2f}" for r in runs) for p in positions))


if __name__ == "__main__":
    main()
