"""The ``mira``, ``mira-no-mcm`` and ``mira-no-srr`` methods: HARS shaping plus MIRA's outer loop."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from mira.config import TrainConfig
from mira.engineer.lsfs import backend_from_config
from mira.methods.hars import describe_shaping, initial_program
from mira.methods.parts import MethodParts
from mira.outer.loop import MiraOuterLoop, save_program_version
from mira.tasks.card import TaskCard
from mira.tasks.envs import action_dim

MODES = {"mira": "full", "mira-no-mcm": "no-mcm", "mira-no-srr": "no-srr"}


def build_mira(config: TrainConfig, card: TaskCard, run_dir: Path, method: str) -> MethodParts:
    from mira.shaping.factors import ProgramFactorSource
    from mira.shaping.source import HarsReward

    mode = MODES[method]
    program = initial_program(config, card, run_dir)
    save_program_version(run_dir / "programs", None, program)
    reward = HarsReward(ProgramFactorSource(program, card), config.hars)
    backend = None
    if mode != "no-srr":
        backend = backend_from_config(config.llm, run_dir / "llm" / "cache", run_dir)
    outer_config = replace(config.mira)  # a copy: resolving ΔT below leaves config.mira as given
    if outer_config.mcm.delta_t is None:  # one cycle per episode (see MCMConfig.delta_t)
        outer_config.mcm = replace(outer_config.mcm, delta_t=int(config.max_episode_steps or card.eval_horizon))
    outer = MiraOuterLoop(outer_config, card, reward, backend, program, action_dim(card), config.llm.followups,
                          gamma=config.agent.gamma, ablation=mode, budget=config.steps)
    what = {"full": "MCM triggers SRR", "no-mcm": "periodic unguided SRR (no MCM)", "no-srr": "MCM only (no SRR)"}
    description = f"MIRA ({what[mode]}) over HARS: {describe_shaping(reward)}"
    return MethodParts(reward, [outer], description)
