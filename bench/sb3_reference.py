"""Stable-Baselines3's SAC on the dense reward: the outside reference for our trainer's learning.

Everything of ours runs through ``mira sweep`` (and ``mira report`` / ``bench/results_page.py`` read it);
this script runs the one thing ``mira train`` cannot, SB3's SAC, with the same networks, batch, schedule
and evaluation protocol (deterministic policy, the same evaluation episode seeds), and writes each run
as a run directory those readers understand: ``OUT/<task>/sac/sb3/seed<k>`` with ``config.json``
(method ``sb3``), ``eval.csv`` written as it goes, and ``status.json`` once it has finished.

    python bench/sb3_reference.py --seeds 0,1,2 --steps 50000 --lr 3e-4 --out bench/runs/sb3
    mira report bench/runs/sb3 bench/runs/SWEEP --out report   # beside our dense SAC of the same grid

Needs the ``bench`` extra (``pip install -e ".[bench]"``).
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from mira.cli import environment_facts
from mira.experiments.grid import parse_seeds
from mira.runio.atomic import atomic_write_json

METHOD = "sb3"


def run_sb3(task: str, seed: int, steps: int, learning_starts: int, eval_every: int, eval_episodes: int,
            out: Path, lr: float) -> Path:
    """One SB3 SAC run on the task's dense reward; returns its run directory."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import SAC

    from mira.loop.evaluation import evaluate
    from mira.loop.trainer import EVAL_SEED_OFFSET
    from mira.runio.csvlog import CsvLog
    from mira.tasks import load_task, make_env

    torch.set_num_threads(1)
    card = load_task(task)
    model = SAC("MlpPolicy", gym.make(card.env_id), learning_rate=lr, buffer_size=1_000_000,
                learning_starts=learning_starts, batch_size=256, tau=0.005, gamma=0.99, train_freq=1,
                gradient_steps=1, ent_coef="auto", policy_kwargs={"net_arch": [256, 256]}, seed=seed,
                device="cpu", verbose=0)
    eval_env = make_env(card, seed=seed + EVAL_SEED_OFFSET)

    class Policy:
        def act(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
            action, _ = model.predict(obs, deterministic=True)
            return np.asarray(action)

    run = out / task / "sac" / METHOD / f"seed{seed}"
    run.mkdir(parents=True, exist_ok=True)
    (run / "status.json").unlink(missing_ok=True)
    (run / "eval.csv").unlink(missing_ok=True)
    config = {"task": task, "method": METHOD, "algo": "sac", "seed": seed, "steps": steps, "program": None,
              "learning_starts": learning_starts, "eval_every": eval_every, "eval_episodes": eval_episodes,
              "agent": {"lr": lr, "batch_size": 256, "hidden": [256, 256], "tau": 0.005, "gamma": 0.99}}
    atomic_write_json(run / "config.json", {"config": config, "environment": environment_facts()})
    log = CsvLog(run / "eval.csv", ["step", "return_mean", "return_std", "wall_s"])
    t0 = time.time()
    done = 0
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(total_timesteps=chunk, reset_num_timesteps=False)
        done += chunk
        result = evaluate(Policy(), eval_env, eval_episodes, seed + EVAL_SEED_OFFSET)  # type: ignore[arg-type]
        log.append({"step": done, "return_mean": result.mean, "return_std": result.std, "wall_s": time.time() - t0})
    atomic_write_json(run / "status.json", {"status": "finished", "step": done})
    return run


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="halfcheetah", help="built-in task (its environment's dense reward)")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=50_000)
    p.add_argument("--learning-starts", type=int, default=10_000)
    p.add_argument("--eval-every", type=int, default=5_000)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--lr", type=float, default=3e-4, help="every optimiser's learning rate (Table 1: 1e-4)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    seeds = parse_seeds(args.seeds)
    with ProcessPoolExecutor(args.workers) as pool:
        jobs = [pool.submit(run_sb3, args.task, s, args.steps, args.learning_starts, args.eval_every,
                            args.eval_episodes, args.out, args.lr) for s in seeds]
        for job in jobs:
            print(f"finished {job.result()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
