"""The ``hars`` method: HARS shaping over an LSFS factor program, no outer loop.

The initial program comes from, in order: ``RUN_DIR/programs/v000.json`` when it exists (a resumed or
re-run run never asks the engineer again), ``config.program`` (a JSON file), or LSFS through the
configured reward engineer (``--llm``: the offline rule-based engineer by default, a script, or an
OpenAI-compatible LLM), with the response cache, budget and audit log of :mod:`mira.engineer.backends`.
Whatever its origin, the program must pass the static checker (compilation refuses anything else)
and is saved atomically as ``RUN_DIR/programs/v000.json`` before training starts.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from mira.errors import UsageError
from mira.shaping.factors import ProgramFactorSource
from mira.shaping.source import HarsReward

if TYPE_CHECKING:
    from mira.config import TrainConfig
    from mira.factors.program import FactorProgram
    from mira.llm.config import LLMConfig
    from mira.methods.parts import MethodParts
    from mira.tasks.card import TaskCard

log = logging.getLogger(__name__)

PROGRAMS_DIR = "programs"


def program_path(run_dir: Path, version: int) -> Path:
    return Path(run_dir) / PROGRAMS_DIR / f"v{version:03d}.json"


def lsfs_program(card: TaskCard, llm: LLMConfig, run_dir: Path) -> FactorProgram:
    """Ask the configured reward engineer for the initial program (section 4.2.1)."""
    from mira.engineer.lsfs import SynthesisError, backend_from_config, synthesize_program
    from mira.tasks.envs import action_dim

    backend = backend_from_config(llm, Path(run_dir) / "llm" / "cache", Path(run_dir))
    try:
        return synthesize_program(card, backend, action_dim(card))
    except SynthesisError as exc:
        raise UsageError(f"LSFS: {exc}") from exc


def initial_program(config: TrainConfig, card: TaskCard, run_dir: Path) -> FactorProgram:
    """The run's program v0 (see module docstring), saved as ``RUN_DIR/programs/v000.json``."""
    from mira.factors.checker import check_program
    from mira.factors.program import load_program
    from mira.runio.atomic import atomic_write_json

    saved = program_path(run_dir, 0)
    if saved.is_file():
        return load_program(saved)
    if config.program:
        program = load_program(config.program)
        if program.task != card.name:
            raise UsageError(f"--program {config.program}: it is a program for task {program.task!r}, "
                             f"not {card.name!r}")
        if program.version != 0:
            log.info("program %s has version %d; it becomes version 0 of this run", config.program,
                     program.version)
            program = replace(program, version=0, parent_version=None, edits=(), diff="")
    else:
        program = lsfs_program(card, config.llm, run_dir)
    report = check_program(program, card.feature_names)
    if not report.ok:
        raise UsageError("factor program v0 is not admissible: " + "; ".join(str(v) for v in report.errors))
    atomic_write_json(saved, program.to_json())
    return program


def build_hars(config: TrainConfig, card: TaskCard, run_dir: Path) -> MethodParts:
    """Method builder for ``--method hars`` (see :data:`mira.methods.METHODS`)."""
    from mira.factors.compiler import InadmissibleCodeError
    from mira.methods.parts import MethodParts

    program = initial_program(config, card, run_dir)
    try:
        source = ProgramFactorSource(program, card)
    except InadmissibleCodeError as exc:
        raise UsageError(f"factor program v0 is not admissible: {exc}") from exc
    reward = HarsReward(source, config.hars)
    return MethodParts(reward, [], f"HARS: {describe_shaping(reward)}, no outer loop")


def describe_shaping(reward: HarsReward) -> str:
    """One line on what the agent learns from (for ``config.json`` and ``mira explain``)."""
    names = ", ".join([*reward.factors.phi_names, *reward.factors.aux_names]) or "none"
    kappa = reward.kappa
    if reward.config.alignment == "episodic":
        return (f"episodic reward + {kappa:g}·PBRS of a potential TD-aligned to it (the paper's letter), "
                f"factors {names}")
    pbrs = f" + {kappa:g}·PBRS of a potential TD-aligned to it" if kappa else ""
    return f"per-step reward decomposed from episodic returns over factors ({names}){pbrs}"
