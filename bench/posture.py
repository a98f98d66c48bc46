"""What a run's policy does: task-card features along its evaluation episodes.

A return says how well a policy did, not where it went. This loads a run's checkpoint, replays the
run's own evaluation episodes (the same seeds, the deterministic policy, so the return matches the
run's ``eval.csv`` at that step) and summarises the named task features over every step: mean, 10th
and 90th percentiles, and the share of steps inside each ``--share`` region: whether a HumanoidStandup
policy sits or stands, or whether the region a flawed program's gate pays in is where the policies go.
``--write`` keeps the summary as ``posture.json`` in the run directory, which ``bench/archive.py``
keeps and the results page (``docs/results.md``) reads.

    python bench/posture.py RUN [RUN ...] --features torso_height,uprightness --share "uprightness<0.3"
    python bench/posture.py RUN --features torso_height --share "torso_height>0.8" --episodes 10 --write
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mira.agents import make_agent
from mira.agents.base import AgentConfig
from mira.config import from_dict
from mira.loop.trainer import EVAL_SEED_OFFSET
from mira.runio.atomic import atomic_write_json
from mira.runio.checkpoint import list_checkpoints, load_checkpoint
from mira.runio.csvlog import read_csv
from mira.tasks import load_task, make_env
from mira.tasks.envs import action_dim

_REGION = re.compile(r"^\s*(\w+)\s*([<>])\s*(-?[\d.]+(?:e-?\d+)?)\s*$")


def parse_region(text: str) -> tuple[str, str, float]:
    """``"feature<value"`` or ``"feature>value"`` → (feature, op, value)."""
    m = _REGION.match(text)
    if m is None:
        raise SystemExit(f"--share {text!r}: expected FEATURE<VALUE or FEATURE>VALUE, e.g. 'uprightness<0.3'")
    return m.group(1), m.group(2), float(m.group(3))


@dataclass
class Posture:
    step: int
    ret: float
    """mean return of the replayed episodes"""
    logged: float | None
    """the run's own evaluation at that step (``eval.csv``), for comparison"""
    features: dict[str, tuple[float, float, float]]
    """feature → (mean, 10th, 90th percentile) over every step"""
    shares: dict[str, float]
    """region → share of the steps inside it"""


def posture(run: Path, features: list[str], regions: list[tuple[str, str, float]], episodes: int,
            step: int | None) -> Posture:
    """Replay ``episodes`` of the run's evaluation at checkpoint ``step`` (default: the latest)."""
    config = json.loads((run / "config.json").read_text(encoding="utf-8"))["config"]
    steps = list_checkpoints(run / "checkpoints")
    if not steps:
        raise SystemExit(f"{run}: no checkpoint in {run / 'checkpoints'}")
    step = steps[-1] if step is None else step
    if step not in steps:
        raise SystemExit(f"{run}: no checkpoint at step {step} (there are: {', '.join(map(str, steps))})")
    card = load_task(config["task"])
    env = make_env(card, seed=config["seed"] + EVAL_SEED_OFFSET, max_episode_steps=config["max_episode_steps"])
    obs_dim = int(env.observation_space.shape[0])  # type: ignore[index]
    for name in features + [r[0] for r in regions]:
        if name not in card.feature_names:
            raise SystemExit(f"{run}: task {card.name!r} has no feature {name!r} "
                             f"(it has: {', '.join(card.feature_names)})")
    agent = make_agent(config["algo"], obs_dim, action_dim(card),
                       from_dict(AgentConfig, config["agent"], "config.agent"), torch.device("cpu"))
    agent.load_state_dict(load_checkpoint(run / "checkpoints", step)["agent"])
    values: dict[str, list[float]] = {name: [] for name in {*features, *(r[0] for r in regions)}}
    returns = []
    for k in range(episodes):
        obs, _ = env.reset(seed=config["seed"] + EVAL_SEED_OFFSET + k)
        total, done = 0.0, False
        while not done:
            obs, _, terminated, truncated, info = env.step(agent.act(obs, deterministic=True))
            total += info["dense_reward"]
            done = terminated or truncated
            row = card.feature_values(obs[None])
            for name in values:
                values[name].append(float(row[name][0]))
        returns.append(total)
    logged = {int(r["step"]): float(r["return_mean"]) for r in read_csv(run / "eval.csv")}
    arrays = {name: np.asarray(v) for name, v in values.items()}
    shares = {f"{f}{op}{v:g}": float(np.mean(arrays[f] < v if op == "<" else arrays[f] > v))
              for f, op, v in regions}
    return Posture(step, float(np.mean(returns)), logged.get(step),
                   {name: (float(arrays[name].mean()), float(np.percentile(arrays[name], 10)),
                           float(np.percentile(arrays[name], 90))) for name in features},
                   shares)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run directories (each with config.json, checkpoints/)")
    p.add_argument("--features", required=True, help="comma-separated task-card features to summarise")
    p.add_argument("--share", action="append", default=[], help="a region FEATURE<VALUE or FEATURE>VALUE "
                   "whose share of the steps is reported (repeatable)")
    p.add_argument("--episodes", type=int, default=5, help="evaluation episodes to replay (the run's first N)")
    p.add_argument("--step", type=int, default=None, help="checkpoint step (default: the latest)")
    p.add_argument("--write", action="store_true", help="also write RUN/posture.json (kept by bench/archive.py)")
    args = p.parse_args()
    torch.set_num_threads(1)
    features = [f.strip() for f in args.features.split(",") if f.strip()]
    regions = [parse_region(r) for r in args.share]
    head = ["run", "step", f"return ({args.episodes} ep.)", "logged eval", *[f"{f} mean [p10, p90]" for f in features],
            *[f"share {r}" for r in args.share]]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for run in args.runs:
        r = posture(run, features, regions, args.episodes, args.step)
        cells = [f"`{run.parent.name}/{run.name}`", str(r.step), f"{r.ret:,.0f}",
                 "-" if r.logged is None else f"{r.logged:,.0f}",
                 *[f"{m:.2f} [{lo:.2f}, {hi:.2f}]" for m, lo, hi in r.features.values()],
                 *[f"{s:.0%}" for s in r.shares.values()]]
        print("| " + " | ".join(cells) + " |")
        if args.write:
            atomic_write_json(run / "posture.json", {
                "step": r.step, "episodes": args.episodes, "return": r.ret, "logged": r.logged,
                "features": {name: {"mean": m, "p10": lo, "p90": hi} for name, (m, lo, hi) in r.features.items()},
                "shares": r.shares})


if __name__ == "__main__":
    main()
