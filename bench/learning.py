"""Learning benchmark: final evaluation return of our methods on HalfCheetah-v5, against SB3's SAC.

Each of our runs is a real ``mira train`` subprocess (so the benchmark measures what users run); the
Stable-Baselines3 reference (a benchmark-only dependency) trains SAC with the same hyperparameters
and budget on the environment's dense reward and is evaluated with the same protocol (deterministic
policy, the same evaluation episode seeds). Results go to ``bench/RESULTS.md`` under "## Learning".

    python bench/learning.py --methods dense --sb3 --seeds 0,1,2 --steps 50000 --workers 2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def run_ours(method: str, algo: str, seed: int, steps: int, out: Path, extra: list[str]) -> dict[str, object]:
    run = out / f"{method}-{algo}-s{seed}"
    if (run / "config.json").exists():  # an interrupted benchmark resumes its runs
        cmd = [sys.executable, "-m", "mira.cli", "train", "--resume", str(run), "--quiet"]
    else:
        cmd = [sys.executable, "-m", "mira.cli", "train", "--task", "halfcheetah", "--method", method, "--algo", algo,
               "--steps", str(steps), "--seed", str(seed), "--out", str(run), "--overwrite", "--threads", "1",
               "--quiet", *extra]
    t0 = time.time()
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL)
    from mira.runio.csvlog import read_csv

    rows = read_csv(run / "eval.csv")
    return {"who": f"mira {method}", "algo": algo, "seed": seed, "wall_s": time.time() - t0,
            "curve": [(int(r["step"]), float(r["return_mean"])) for r in rows]}


def run_sb3(seed: int, steps: int, learning_starts: int, eval_every: int, eval_episodes: int) -> dict[str, object]:
    import torch
    from stable_baselines3 import SAC

    from mira.loop.evaluation import evaluate
    from mira.loop.trainer import EVAL_SEED_OFFSET
    from mira.tasks import load_task, make_env

    torch.set_num_threads(1)
    card = load_task("halfcheetah")
    import gymnasium as gym

    env = gym.make(card.env_id)
    model = SAC("MlpPolicy", env, learning_rate=1e-4, buffer_size=1_000_000, learning_starts=learning_starts,
                batch_size=256, tau=0.005, gamma=0.99, train_freq=1, gradient_steps=1, ent_coef="auto",
                policy_kwargs={"net_arch": [256, 256]}, seed=seed, device="cpu", verbose=0)
    eval_env = make_env(card, seed=seed + EVAL_SEED_OFFSET)

    class Policy:
        def act(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
            action, _ = model.predict(obs, deterministic=True)
            return np.asarray(action)

    t0 = time.time()
    curve = []
    done = 0
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(total_timesteps=chunk, reset_num_timesteps=False)
        done += chunk
        result = evaluate(Policy(), eval_env, eval_episodes, seed + EVAL_SEED_OFFSET)  # type: ignore[arg-type]
        curve.append((done, result.mean))
    return {"who": "sb3 SAC", "algo": "sac", "seed": seed, "wall_s": time.time() - t0, "curve": curve}


def final_return(curve: list[tuple[int, float]], steps: int) -> float:
    """Asymptotic performance: mean eval return over the final 10% of training (at least the last)."""
    tail = [r for s, r in curve if s > 0.9 * steps] or [curve[-1][1]]
    return float(np.mean(tail))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--methods", default="dense")
    p.add_argument("--algo", default="sac")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=50_000)
    p.add_argument("--learning-starts", type=int, default=10_000)
    p.add_argument("--eval-every", type=int, default=5_000)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--sb3", action="store_true", help="also run Stable-Baselines3's SAC (dense reward)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "runs" / "learning")
    p.add_argument("--train-args", default="", help="extra flags for mira train")
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    extra = ["--learning-starts", str(args.learning_starts), "--eval-every", str(args.eval_every),
             "--eval-episodes", str(args.eval_episodes), *args.train_args.split()]
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = []
    with ProcessPoolExecutor(args.workers) as pool:
        for method in args.methods.split(","):
            for seed in seeds:
                jobs.append(pool.submit(run_ours, method, args.algo, seed, args.steps, args.out, extra))
        if args.sb3:
            for seed in seeds:
                jobs.append(pool.submit(run_sb3, seed, args.steps, args.learning_starts, args.eval_every,
                                        args.eval_episodes))
        results = [j.result() for j in jobs]
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    by_who: dict[str, list[float]] = {}
    walls: dict[str, list[float]] = {}
    for r in results:
        by_who.setdefault(str(r["who"]), []).append(final_return(r["curve"], args.steps))  # type: ignore[arg-type]
        walls.setdefault(str(r["who"]), []).append(float(r["wall_s"]))  # type: ignore[arg-type]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    lines = [
        f"HalfCheetah-v5, {args.algo.upper()}, {args.steps} steps, seeds {args.seeds}, eval every {args.eval_every} "
        f"steps x {args.eval_episodes} episodes; figure = mean eval return over the final 10% of training.",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, 1 torch thread per run, "
        f"{args.workers} runs in parallel; commit {commit}.",
        "",
        "| method | final return (mean ± std over seeds) | per-seed | wall s / run |",
        "|---|---|---|---|",
    ]
    for who, vals in by_who.items():
        lines.append(f"| {who} | {np.mean(vals):.1f} ± {np.std(vals):.1f} | "
                     f"{', '.join(f'{v:.0f}' for v in vals)} | {np.mean(walls[who]):.0f} |")
    table = "\n".join(lines)
    print(table)
    (args.out / "table.md").write_text(table + "\n")


if __name__ == "__main__":
    main()
