"""The ``hars`` method: HARS shaping over an LSFS factor program, no outer loop.

The initial program comes from, in order: ``RUN_DIR/programs/v000.json`` when it exists (a resumed or
re-run run never asks the engineer again), ``config.program`` (a JSON file), or LSFS through the
configured reward engineer (``--llm``: the offline rule-based engineer by default, a script, or an
OpenAI-compatible LLM), with the response cache, budget and audit log of :mod:`mira.engineer.backends`.
Whatever its origin, the program passes the gates an edit passes (static checks, then the sandbox on
real states) and is saved atomically as ``RUN_DIR/programs/v000.json`` before training starts.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
ORIGIN_FILE = "origin.json"
"""Who wrote program v0: the LLM (with its attempts), the offline engineer (and why), or a file."""


def program_path(run_dir: Path, version: int) -> Path:
    return Path(run_dir) / PROGRAMS_DIR / f"v{version:03d}.json"


def lsfs_program(card: TaskCard, llm: LLMConfig, run_dir: Path) -> tuple[FactorProgram, dict[str, Any]]:
    """Ask the configured reward engineer for the initial program (section 4.2.1), with ``llm.followups``
    follow-up turns for a refused reply; when every attempt is refused, the offline engineer's program
    is used and the run says so (a warning, and ``programs/origin.json``)."""
    from mira.engineer.backends import make_backend
    from mira.engineer.lsfs import SynthesisError, backend_from_config, synthesize_program
    from mira.tasks.envs import action_dim

    backend = backend_from_config(llm, Path(run_dir) / "llm" / "cache", Path(run_dir))
    try:
        made = synthesize_program(card, backend, action_dim(card), followups=llm.followups)
    except SynthesisError as exc:
        if llm.backend == "offline":
            raise UsageError(f"LSFS: {exc}") from exc
        log.warning("LSFS: %s; the run starts from the offline rule-based engineer's program instead", exc)
        offline = make_backend("offline", audit_dir=Path(run_dir))
        try:
            made = synthesize_program(card, offline, action_dim(card))
        except SynthesisError as inner:
            raise UsageError(f"LSFS: {exc}; the offline engineer's fallback failed too: {inner}") from inner
        return made.program, {"written_by": "offline", "fallback_from": llm.backend, "reason": str(exc),
                              "attempts": [a.as_dict() for a in exc.attempts], "warnings": made.warnings}
    return made.program, {"written_by": llm.backend, "attempts": [a.as_dict() for a in made.attempts],
                          "warnings": made.warnings}


def initial_program(config: TrainConfig, card: TaskCard, run_dir: Path) -> FactorProgram:
    """The run's program v0 (see module docstring), saved as ``RUN_DIR/programs/v000.json`` with who wrote
    it in ``RUN_DIR/programs/origin.json``."""
    from mira.engineer.admission import admit_program
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
        gates = admit_program(program, card)
        if not gates.ok:
            raise UsageError(f"--program {config.program}: not admissible: " + "; ".join(gates.errors))
        origin: dict[str, Any] = {"written_by": "file", "file": str(config.program), "warnings": gates.warnings}
    else:
        program, origin = lsfs_program(card, config.llm, run_dir)
    for warning in origin["warnings"]:
        log.warning("program v0: %s", warning)
    atomic_write_json(saved, program.to_json())
    atomic_write_json(Path(run_dir) / PROGRAMS_DIR / ORIGIN_FILE, origin)
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
