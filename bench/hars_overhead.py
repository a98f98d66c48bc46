"""Cost of HARS on top of the agent: ``python bench/hars_overhead.py [--task T] [--algo A] ...``.

Measures, on random transitions (costs do not depend on the values):

* the added wall time per training step: ``agent.update(batch, shaped); hars.update(...)``, the
  batches before each HARS training step shaped together as the trainer does (``relabel_many``),
  against the same agent on the sparse reward ``agent.update(batch, batch.reward)``, interleaved so
  that machine load hits both alike; means, medians and minima over many steps are reported (HARS
  trains and shapes on some steps only, so the mean is its cost per step);
* ``on_transition`` (factor evaluation per stored step);
* ``recompute_all`` on a full buffer (default 1M transitions).

This is a measurement script, not a test; nothing here runs in the test suite.
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

from mira.agents import make_agent
from mira.agents.base import AgentConfig
from mira.factors.examples import example_program
from mira.replay import ReplayBuffer
from mira.rewards.base import RewardContext
from mira.shaping.columns import RECOMPUTE_CHUNK
from mira.shaping.config import HarsConfig
from mira.shaping.factors import ProgramFactorSource
from mira.shaping.source import HarsReward
from mira.tasks.card import load_task
from mira.tasks.envs import make_env


def _fill(buf: ReplayBuffer, n: int, rng: np.random.Generator, episode_len: int = 1000) -> None:
    """Write ``n`` random transitions straight into the buffer's columns (fast, no env)."""
    obs = torch.from_numpy(rng.normal(size=(n, buf.obs_dim)).astype(np.float32))
    buf.obs[:n] = obs
    buf.next_obs[:n] = obs + 0.01
    buf.action[:n] = torch.from_numpy(rng.uniform(-1, 1, size=(n, buf.act_dim)).astype(np.float32))
    steps = torch.arange(n) % episode_len
    buf.episode_id[:n] = torch.arange(n) // episode_len
    buf.episode_step[:n] = steps
    buf.reward[:n] = torch.where(steps == episode_len - 1, 100.0, 0.0)
    buf.truncated[:n] = (steps == episode_len - 1).float()
    buf.size = n
    buf.pos = n % buf.capacity


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--algo", default="sac", choices=("sac", "ddpg"))
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--steps", type=int, default=300, help="timed training steps per arm")
    p.add_argument("--transitions", type=int, default=100_000, help="buffer rows for the step timing")
    p.add_argument("--recompute-rows", type=int, default=1_000_000, help="0: skip the recompute timing")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--hars", default="{}", help="HarsConfig overrides as JSON, e.g. '{\"update_every\": 1}'")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)

    card = load_task(args.task)
    env = make_env(card)
    obs_dim, act_dim = int(env.observation_space.shape[0]), int(env.action_space.shape[0])  # type: ignore[index]
    env.close()
    source = ProgramFactorSource(example_program(args.task), card)
    cfg = AgentConfig(hidden=(args.hidden, args.hidden), batch_size=args.batch_size)
    device = torch.device("cpu")
    agent = make_agent(args.algo, obs_dim, act_dim, cfg, device)

    buf = ReplayBuffer(args.transitions, obs_dim, act_dim)
    hars_cfg = HarsConfig(**json.loads(args.hars))
    hars = HarsReward(source, hars_cfg)
    hars.bind(RewardContext(card, obs_dim, act_dim, cfg.gamma, device, buf, 0, Path(".")))
    # on_transition: the per-environment-step cost
    t_on = []
    for _ in range(2000):
        o = rng.normal(size=obs_dim).astype(np.float32)
        row = buf.add(o, rng.uniform(-1, 1, act_dim).astype(np.float32), 0.0, 0.0, o, False, False, 0)
        t0 = time.perf_counter()
        hars.on_transition(row)
        t_on.append(time.perf_counter() - t0)
    _fill(buf, args.transitions, rng)
    hars.columns.recompute_all(RECOMPUTE_CHUNK)

    def sparse_step() -> float:
        batch = buf.sample(args.batch_size, rng)
        t0 = time.perf_counter()
        agent.update(batch, batch.reward)
        return time.perf_counter() - t0

    ahead: list[tuple[Any, torch.Tensor]] = []

    def hars_step() -> float:
        # As the trainer does it: the batches before HARS's next training step are sampled and shaped
        # together (``lookahead`` / ``relabel_many``); that pass is timed in the step that makes it.
        t0 = time.perf_counter()
        if not ahead:
            batches = [buf.sample(args.batch_size, rng) for _ in range(hars.lookahead())]
            t0 = time.perf_counter()
            ahead.extend(zip(batches, hars.relabel_many(batches), strict=True))
        batch, shaped = ahead.pop(0)
        agent.update(batch, shaped)
        hars.update(batch, 0)
        return time.perf_counter() - t0

    for _ in range(20):
        sparse_step()
        hars_step()
    ts, th = [], []
    for _ in range(args.steps):
        ts.append(sparse_step())
        th.append(hars_step())
    med_s, med_h = statistics.median(ts), statistics.median(th)
    # HARS trains on every `update_every`-th batch only, so its cost per step is the mean, not the median.
    mean_s, mean_h = statistics.fmean(ts), statistics.fmean(th)
    min_s, min_h = min(ts), min(th)

    # recompute_all on a full buffer of `recompute_rows` transitions
    t_re = float("nan")
    if args.recompute_rows > 0:
        del buf
        big = ReplayBuffer(args.recompute_rows, obs_dim, act_dim)
        _fill(big, args.recompute_rows, rng)
        hars_big = HarsReward(ProgramFactorSource(example_program(args.task), card), hars_cfg)
        hars_big.bind(RewardContext(card, obs_dim, act_dim, cfg.gamma, device, big, 0, Path(".")))
        t0 = time.perf_counter()
        hars_big.columns.recompute_all(RECOMPUTE_CHUNK)
        t_re = time.perf_counter() - t0

    out = {
        "task": args.task, "algo": args.algo, "hidden": args.hidden, "batch_size": args.batch_size,
        "threads": args.threads, "hars_overrides": json.loads(args.hars),
        "update_every": hars_cfg.update_every,
        "sparse_update_ms_mean": 1e3 * mean_s, "hars_update_ms_mean": 1e3 * mean_h,
        "added_ms_mean": 1e3 * (mean_h - mean_s), "overhead_mean_pct": 100 * (mean_h - mean_s) / mean_s,
        "sparse_update_ms_median": 1e3 * med_s, "hars_update_ms_median": 1e3 * med_h,
        "added_ms_median": 1e3 * (med_h - med_s), "overhead_median_pct": 100 * (med_h / med_s - 1),
        "sparse_update_ms_min": 1e3 * min_s, "hars_update_ms_min": 1e3 * min_h,
        "added_ms_min": 1e3 * (min_h - min_s), "overhead_min_pct": 100 * (min_h / min_s - 1),
        "on_transition_us_median": 1e6 * statistics.median(t_on),
        "recompute_all_rows": args.recompute_rows, "recompute_all_s": t_re,
    }
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
