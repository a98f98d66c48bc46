"""Learning benchmark: final evaluation return of our methods on a task (HalfCheetah-v5 by default),
against SB3's SAC.

Each of our runs is a real ``mira train`` subprocess (so the benchmark measures what users run); the
Stable-Baselines3 reference (a benchmark-only dependency) trains SAC with the same hyperparameters
and budget on the environment's dense reward and is evaluated with the same protocol (deterministic
policy, the same evaluation episode seeds). Results go to ``bench/RESULTS.md`` under "## Learning".

    python bench/learning.py --methods dense --sb3 --seeds 0,1,2 --steps 50000 --workers 2
    python bench/learning.py --table-only --out bench/runs/learning   # rebuild the table from run dirs
    python bench/learning.py --table-only --out bench/runs/l100k --steps 100000 --at 50000,100000

The table gives, per method and budget, the interquartile mean over seeds of the final return (the
mean evaluation return over the final 10% of the budget) with a 95% bootstrap confidence interval,
and each seed's figure. ``--at`` reads smaller budgets off the same (longer) runs' evaluations.

Every run writes its evaluation curve as it goes (``<out>/<who>-<algo>-s<seed>/eval.csv``, SB3's
included), so a benchmark stopped by a time limit still yields a table of the budgets its runs
reached (a run is left out of a budget it has not reached). ``bench/archive.py`` keeps the curves in
git, so a table can be rebuilt, and a grid filled, after the run directories are gone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from mira.cli import cpu_model
from mira.experiments.metrics import asymptotic_performance, stratified_bootstrap_ci

ROOT = Path(__file__).resolve().parents[1]


def run_ours(method: str, algo: str, seed: int, steps: int, out: Path, extra: list[str],
             task: str = "halfcheetah", suffix: str = "") -> None:
    """One `mira train` run; its curve is the run directory's own eval.csv."""
    run = out / f"{method}{suffix}-{algo}-s{seed}"
    if (run / "config.json").exists():  # an interrupted benchmark resumes its runs
        # ``--steps`` also extends a finished run to a larger budget from its last checkpoint.
        cmd = [sys.executable, "-m", "mira.cli", "train", "--resume", str(run), "--steps", str(steps), "--quiet"]
    else:
        cmd = [sys.executable, "-m", "mira.cli", "train", "--task", task, "--method", method, "--algo", algo,
               "--steps", str(steps), "--seed", str(seed), "--out", str(run), "--overwrite", "--threads", "1",
               "--quiet", *extra]
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL)


def run_sb3(seed: int, steps: int, learning_starts: int, eval_every: int, eval_episodes: int,
            out: Path, lr: float = 1e-4) -> None:
    """SB3's SAC on the dense reward, its curve written to ``<out>/sb3-sac-s<seed>/eval.csv`` as it goes."""
    import torch
    from stable_baselines3 import SAC

    from mira.loop.evaluation import evaluate
    from mira.loop.trainer import EVAL_SEED_OFFSET
    from mira.tasks import load_task, make_env

    torch.set_num_threads(1)
    card = load_task("halfcheetah")
    import gymnasium as gym

    env = gym.make(card.env_id)
    model = SAC("MlpPolicy", env, learning_rate=lr, buffer_size=1_000_000, learning_starts=learning_starts,
                batch_size=256, tau=0.005, gamma=0.99, train_freq=1, gradient_steps=1, ent_coef="auto",
                policy_kwargs={"net_arch": [256, 256]}, seed=seed, device="cpu", verbose=0)
    eval_env = make_env(card, seed=seed + EVAL_SEED_OFFSET)

    class Policy:
        def act(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
            action, _ = model.predict(obs, deterministic=True)
            return np.asarray(action)

    from mira.runio.csvlog import CsvLog

    run = out / f"sb3-sac-s{seed}"
    run.mkdir(parents=True, exist_ok=True)
    (run / "eval.csv").unlink(missing_ok=True)
    log = CsvLog(run / "eval.csv", ["step", "return_mean", "return_std", "wall_s"])
    t0 = time.time()
    done = 0
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(total_timesteps=chunk, reset_num_timesteps=False)
        done += chunk
        result = evaluate(Policy(), eval_env, eval_episodes, seed + EVAL_SEED_OFFSET)  # type: ignore[arg-type]
        log.append({"step": done, "return_mean": result.mean, "return_std": result.std, "wall_s": time.time() - t0})


def collect(out: Path) -> dict[str, list[tuple[int, list[tuple[int, float]], float]]]:
    """Read every run directory under ``out``: who → [(seed, curve, wall seconds)]."""
    from mira.runio.csvlog import read_csv

    found: dict[str, list[tuple[int, list[tuple[int, float]], float]]] = {}
    for eval_csv in sorted(out.glob("*-s*/eval.csv")):
        name = eval_csv.parent.name
        stem, _, seed = name.rpartition("-s")
        who, _, algo = stem.rpartition("-")
        rows = read_csv(eval_csv)
        if not rows or not seed.isdigit():
            continue
        curve = [(int(r["step"]), float(r["return_mean"])) for r in rows]
        wall = float(rows[-1].get("wall_s") or "nan")
        label = "SB3 SAC" if who == "sb3" else who
        found.setdefault(f"{label} ({algo})", []).append((int(seed), curve, wall))
    return found


def run_sources(roots: list[Path]) -> str:
    """The code the runs under ``roots`` ran, as each run's ``config.json`` records it (``source``):
    every commit, shortened and marked where ``src/`` had uncommitted changes, with its number of runs;
    runs from before that record count as unrecorded. A table read from an archive thus names the code
    that produced it, not the tree it was printed from."""
    counts: Counter[str] = Counter()
    for config in sorted(p for root in roots if root.is_dir() for p in root.rglob("config.json")):
        try:
            source = (json.loads(config.read_text()).get("environment") or {}).get("source")
        except (OSError, ValueError, AttributeError):
            source = None
        commit, _, digest = str(source or "").partition("+")
        counts[(commit[:7] + ("+changes" if digest else "")) if commit else "unrecorded"] += 1
    return ", ".join(f"{code} ({n} run{'s' * (n != 1)})" for code, n in sorted(counts.items())) or "no runs"


def final_return(curve: list[tuple[int, float]], budget: int) -> float | None:
    """Mean evaluation return over the final 10% of ``budget`` (None if the run did not reach it)."""
    points = [(s, r) for s, r in curve if s <= budget]
    if not points or max(s for s, _ in points) < budget:
        return None
    return asymptotic_performance([s for s, _ in points], [r for _, r in points], budget)


def table(out: Path, steps: int, header: list[str], budgets: list[int] | None = None) -> str:
    budgets = budgets or [steps]
    lines = [*header, "", "| method | budget | final return: IQM [95% CI] | mean ± std | per seed | seeds | "
             "wall s / run |", "|---|---|---|---|---|---|---|"]
    for who, runs in sorted(collect(out).items()):
        walls = [w for _, curve, w in runs if np.isfinite(w) and max(s for s, _ in curve) >= max(budgets)]
        wall = f"{np.mean(walls):.0f}" if walls else "-"
        for budget in budgets:
            per_seed = sorted((seed, final_return(curve, budget)) for seed, curve, _ in runs)
            done = [(seed, v) for seed, v in per_seed if v is not None]
            if not done:
                continue
            values = [v for _, v in done]
            point, lo, hi = stratified_bootstrap_ci([values])
            lines.append(f"| {who} | {budget // 1000}k | {point:.0f} [{lo:.0f}, {hi:.0f}] | {np.mean(values):.0f} ± "
                         f"{np.std(values):.0f} | {', '.join(f's{seed} {v:.0f}' for seed, v in done)} | "
                         f"{len(done)} | {wall} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--methods", default="dense")
    p.add_argument("--task", default="halfcheetah", help="built-in task or task card (SB3's reference: HalfCheetah)")
    p.add_argument("--at", default="", help="budgets to tabulate, e.g. 50000,100000 (default: --steps)")
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
    p.add_argument("--suffix", default="", help="appended to the method in run names, e.g. +kappa1 for a variant")
    p.add_argument("--lr", type=float, default=3e-4, help="every optimiser's learning rate (Table 1: 1e-4)")
    p.add_argument("--table-only", action="store_true", help="only rebuild the table from the run directories")
    p.add_argument("--commit", default=os.environ.get("MIRA_COMMIT", ""),
                   help="commit the table names as the tree it was printed from (default: HEAD)")
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    extra = ["--learning-starts", str(args.learning_starts), "--lr", str(args.lr), "--eval-every", str(args.eval_every),
             "--eval-episodes", str(args.eval_episodes), *args.train_args.split()]
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        with ProcessPoolExecutor(args.workers) as pool:
            jobs = [pool.submit(run_sb3, seed, args.steps, args.learning_starts, args.eval_every, args.eval_episodes,
                                args.out, args.lr) for seed in (seeds if args.sb3 else [])]
            for seed in seeds:  # seed-major: a benchmark stopped early has every method on its first seeds
                for method in args.methods.split(","):
                    jobs.append(pool.submit(run_ours, method, args.algo, seed, args.steps, args.out, extra, args.task,
                                            args.suffix))
            for job in jobs:
                job.result()
    commit = args.commit or subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                           cwd=ROOT).stdout.strip()
    header = [
        f"{args.task}, {args.algo.upper()}, {args.steps} steps, seeds {args.seeds}, learning starts "
        f"{args.learning_starts}, lr {args.lr:g}, eval every {args.eval_every} steps x {args.eval_episodes} episodes; "
        "figure = mean "
        "eval return over the final 10% of the steps reached.",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores, 1 torch thread per run, "
        f"{args.workers} runs in parallel; runs' code {run_sources([args.out])}; table printed at {commit}; "
        f"extra train flags: {args.train_args or 'none'}.",
    ]
    budgets = [int(b) for b in args.at.split(",") if b] or [args.steps]
    text = table(args.out, args.steps, header, budgets)
    print(text)
    (args.out / "table.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
