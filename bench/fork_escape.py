"""The escape edit the monitor would make at a run's checkpoint, written as a program for ``--fork-program``.

A paired test of the escape (issue: beyond the dense oracle on HumanoidStandup) forks one plateaued
checkpoint into runs with the escape installed and runs without it, with the same seeds on one machine
(``mira train --fork``). This writes the escape program: the run's held-out episodes at the checkpoint
are replayed as the outer loop replays them each cycle (its held-out seeds, the deterministic policy),
the plateau report is built from them as the plateau detector builds it (the band where the episodes
settle, the range they visit, where they start, the reward per step), and the offline engineer's
:func:`~mira.engineer.offline_srr.add_escape_potential` adds its SHAPE factor to the program in force.

    python bench/fork_escape.py RUN --step 200000 --out escape.json [--reward-steps 20]
    mira train --fork RUN --fork-step 200000 --steps 230000 --seed 11 --method mira-no-srr \\
        --fork-program escape.json --out runs/escape-s11
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from mira.agents import make_agent
from mira.agents.base import AgentConfig
from mira.config import from_dict
from mira.engineer.offline_srr import ESCAPE_STEPS, add_escape_potential
from mira.factors.program import FactorProgram
from mira.loop.evaluation import collect_rollout
from mira.loop.trainer import EVAL_SEED_OFFSET, HOLDOUT_SEED_OFFSET
from mira.mcm.band import stagnation_band
from mira.mcm.plateau import first_states, late_states
from mira.runio.checkpoint import load_checkpoint
from mira.runio.fork import program_version_at
from mira.tasks import load_task, make_env
from mira.tasks.envs import action_dim


def plateau_report(run: Path, step: int) -> tuple[dict, FactorProgram]:
    """The plateau report of the run's held-out episodes at checkpoint ``step``, and the program in force."""
    saved = json.loads((run / "config.json").read_text(encoding="utf-8"))["config"]
    card = load_task(saved["task"])
    if card.band_feature is None:
        raise SystemExit(f"{run}: task {card.name!r} names no band feature")
    env = make_env(card, seed=saved["seed"] + EVAL_SEED_OFFSET, max_episode_steps=saved["max_episode_steps"])
    state = load_checkpoint(run / "checkpoints", step)
    agent = make_agent(saved["algo"], int(env.observation_space.shape[0]), action_dim(card),  # type: ignore[index]
                       from_dict(AgentConfig, saved["agent"], "config.agent"), torch.device("cpu"))
    agent.load_state_dict(state["agent"])
    rollout = collect_rollout(agent, env, int(saved["mira"]["holdout_episodes"]), saved["seed"] + HOLDOUT_SEED_OFFSET)
    feature = card.feature_values(rollout.obs)[card.band_feature]
    center, half = stagnation_band(late_states(feature, rollout.episode_index))
    recent = float(rollout.returns.mean())
    report = {"feature": card.band_feature, "center": center, "halfwidth": half,
              "visited": [float(np.percentile(feature, 1)), float(np.percentile(feature, 99))],
              "start": float(np.median(first_states(feature, rollout.episode_index))),
              "reward_per_step": recent / max(1.0, len(rollout.obs) / max(1, len(rollout.returns))),
              "held_out_return": recent}
    version = program_version_at(state)
    program_file = run / "programs" / f"v{0 if version is None else version:03d}.json"
    return report, FactorProgram.from_json(json.loads(program_file.read_text(encoding="utf-8")))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a run directory with a checkpoint at --step")
    p.add_argument("--step", type=int, required=True, help="the checkpoint to fork from")
    p.add_argument("--out", type=Path, required=True, help="the program file to write")
    p.add_argument("--from-band", action="store_true",
                   help="a variant: Ψ = β·max(0, tanh((z − center)/w)), zero on and below the band (the engineer's "
                        "ramp is about 0.27β there, which shifts the critic's values of the states the policy visits)")
    p.add_argument("--reward-steps", type=float, default=ESCAPE_STEPS,
                   help=f"the potential's height in steps of the plateau's reward (default {ESCAPE_STEPS:g}, "
                        "the offline engineer's)")
    args = p.parse_args()
    torch.set_num_threads(1)
    report, program = plateau_report(args.run, args.step)
    ev = SimpleNamespace(plateau=report, factors=[f.to_json() for f in program.factors])
    made = add_escape_potential(ev, steps=args.reward_steps)  # type: ignore[arg-type]
    assert made is not None
    edit, factors = made
    if args.from_band:
        params = edit["params"]
        name, feature, width, beta = params["new_factor"], params["feature"], params["ramp_width"], params["height"]
        code = (f"def {name}(s):\n    return {beta:.6f} * np.maximum(0.0, np.tanh((s.{feature} - "
                f"{report['center']:.6f}) / {width:.6f}))\n")
        factors[-1] = {**factors[-1], "code": code,
                       "doc": f"escape potential from the band {feature} = {report['center']:.6g} up: 0 on and below "
                              f"it, rising over {width:.6g} to {beta:.6g}"}
        params["code"], params["form"] = code, "from the band"
    out = program.to_json()
    out.update(factors=factors, version=0, parent_version=None, edits=[], diff="",
               rationale=f"{edit['justification']} ({args.reward_steps:g} steps of the plateau's reward)")
    args.out.write_text(json.dumps(out, indent=2) + "\n", encoding="utf-8")
    print(json.dumps({"plateau": report, "escape": edit["params"]}, indent=2))


if __name__ == "__main__":
    main()
