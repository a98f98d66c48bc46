"""What one HARS training step costs, standalone: ``python bench/hars_train_step.py [--profile]``.

Builds a HARS source over a synthetic 100k-row HalfCheetah buffer (the task's offline program, Table 1
networks, batch 256), trains it on every batch (``update_every = 1``) and times the two halves of a
training step: ``relabel`` (the forward with a graph over [s; s′] and, on every ``TCE_EVERY``-th
step, the TCE's context rows) and ``update`` (losses, backward, Adam, figures). A stand-in critic
gradient is put on the shaped reward so the joint term is exercised. ``--profile`` prints
torch.profiler's table of the ops behind it (counts per step and time), which is where to look
before writing faster code: at these sizes a step is hundreds of small ops, not a few products.

This measures HARS alone, with warm caches; inside the training loop the same step runs slower
(the agent's update in between evicts HARS's data), see ``bench/loop_phases.py``. A measurement
script, not a test.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hars_overhead import _fill  # the same synthetic buffer (run as a script, bench/ is on sys.path)
from mira.factors.examples import example_program
from mira.replay import ReplayBuffer
from mira.rewards.base import RewardContext
from mira.shaping.columns import RECOMPUTE_CHUNK
from mira.shaping.config import HarsConfig
from mira.shaping.factors import ProgramFactorSource
from mira.shaping.source import HarsReward
from mira.tasks.card import load_task
from mira.tasks.envs import make_env


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--steps", type=int, default=400, help="timed training steps (after 50 warm-up steps)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--hars", default="{}", help="HarsConfig overrides as JSON (update_every is forced to 1)")
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's op table")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)

    card = load_task(args.task, check_env=False)
    env = make_env(card)
    obs_dim, act_dim = int(env.observation_space.shape[0]), int(env.action_space.shape[0])  # type: ignore[index]
    env.close()
    buf = ReplayBuffer(100_000, obs_dim, act_dim)
    _fill(buf, 100_000, rng)
    cfg = HarsConfig(**{**json.loads(args.hars), "update_every": 1})
    hars = HarsReward(ProgramFactorSource(example_program(args.task), card), cfg)
    hars.bind(RewardContext(card, obs_dim, act_dim, 0.99, torch.device("cpu"), buf, 0, Path(".")))
    hars.columns.recompute_all(RECOMPUTE_CHUNK)
    critic_grad = torch.linspace(-1.0, 1.0, args.batch_size) * 1e-2

    def step(i: int) -> tuple[float, float]:
        batch = buf.sample(args.batch_size, rng)
        t0 = time.perf_counter()
        reward = hars.relabel(batch)
        t1 = time.perf_counter()
        if reward.requires_grad:
            (reward * critic_grad).sum().backward()
        t2 = time.perf_counter()
        hars.update(batch, i)
        return t1 - t0, time.perf_counter() - t2

    for i in range(50):
        step(i)
    times = [step(50 + i) for i in range(args.steps)]
    relabel_ms = [1e3 * a for a, _ in times]
    update_ms = [1e3 * b for _, b in times]
    result = {"task": args.task, "batch_size": args.batch_size, "threads": args.threads, "hars": json.loads(args.hars),
              "relabel_ms_mean": statistics.fmean(relabel_ms), "update_ms_mean": statistics.fmean(update_ms),
              "step_ms_mean": statistics.fmean(a + b for a, b in zip(relabel_ms, update_ms, strict=True)),
              "update_ms_median": statistics.median(update_ms)}
    print(json.dumps(result, indent=1))
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for i in range(100):
                step(10_000 + i)
        print("(100 training steps; divide counts and times by 100 for one step)")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30))
    return result


if __name__ == "__main__":
    main()
