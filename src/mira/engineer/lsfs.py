"""Linguistic-Semantic Factor Synthesis (section 4.2.1): the initial factor program of a task.

One entry point for every caller (``mira factors synth``, HARS/MIRA, LaRe): build the structured
prompt from the task card, ask the configured backend (an LLM, a script, or the offline rule-based
engineer — the caller never knows which), read the reply as models write it, and pass the program
through the same gates as an edit (static checks, then the sandbox on real states) before anyone uses
it; a refused reply goes back to the model with its errors (:mod:`mira.engineer.dialogue`). The
backend is built from an :class:`~mira.config.LLMConfig` with the response cache on by default and
every exchange audited in the run directory.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from mira.engineer.admission import Admission, admit_program, with_code
from mira.engineer.backends import make_backend
from mira.engineer.dialogue import Attempt, Verdict, converse
from mira.engineer.lsfs_prompt import build_lsfs_messages, parse_program_reply
from mira.errors import MiraError
from mira.factors.checker import check_program
from mira.factors.program import FactorProgram, ProgramParseError
from mira.llm.base import LLMBackend, LLMRequest
from mira.llm.config import LLMConfig
from mira.tasks.card import TaskCard

Purpose = Literal["lsfs", "srr", "lare"]


Admitted = tuple[FactorProgram, list[str]]
"""An admitted program with the warnings of its checks."""


class SynthesisError(MiraError):
    """The backend's program could not be parsed or is not admissible, after every follow-up turn."""

    def __init__(self, message: str, *, attempts: list[Attempt] | None = None) -> None:
        super().__init__(message)
        self.attempts = attempts or []


def backend_from_config(cfg: LLMConfig, default_cache: Path | None, audit_dir: Path | None) -> LLMBackend:
    """The configured backend with cache (default ``default_cache``), budget and audit."""
    cache = Path(cfg.cache_dir) if cfg.cache_dir else default_cache
    return make_backend(
        cfg.backend, base_url=cfg.base_url, api_key_env=cfg.api_key_env, cache_dir=cache,
        offline_only=cfg.offline_only, audit_dir=audit_dir, max_calls=cfg.max_calls,
        max_tokens_total=cfg.max_tokens_total, timeout_s=cfg.timeout_s, max_retries=cfg.max_retries,
    )


def observed_ranges(card: TaskCard) -> dict[str, list[float]]:
    """Each feature's [min, max] over the sandbox's real states (a random policy's rollouts): what the
    offline engineer's range hints are computed from. Empty when the environment cannot be built."""
    from mira.factors.sandbox import collect_states

    try:
        obs, _ = collect_states(card)
    except MiraError:  # a card whose environment cannot be built is reported where it is built
        return {}
    out = {}
    for name, values in card.feature_values(obs).items():
        v = np.asarray(values, dtype=np.float64)
        if v.size and np.all(np.isfinite(v)):
            out[name] = [float(v.min()), float(v.max())]
    return out


def lsfs_request(card: TaskCard, action_dim: int, purpose: Purpose = "lsfs") -> LLMRequest:
    ranges = observed_ranges(card)
    messages = build_lsfs_messages(card, action_dim)
    context = {
        "task": card.name,
        "features": [{"name": f.name, "units": f.units, "doc": f.doc, "better": f.better, "target": f.target,
                      "range": ranges.get(f.name)} for f in card.features],
        "action_dim": action_dim,
        "description": card.description,
    }
    return LLMRequest(messages=messages, purpose=purpose, temperature=0.0, context=context)


@dataclass
class Synthesis:
    """An admitted initial program, how many turns it took, and what a person should know about it."""

    program: FactorProgram
    attempts: list[Attempt]
    warnings: list[str] = field(default_factory=list)

    @property
    def retries(self) -> int:
        return len(self.attempts) - 1


def judge_program(card: TaskCard, sandbox: bool = True) -> Callable[[str], Verdict[Admitted]]:
    """Parse a reply as a program and pass it through the static checks and (``sandbox``) the sandbox."""

    def judge(content: str) -> Verdict[Admitted]:
        try:
            program = parse_program_reply(content, card)
        except ProgramParseError as exc:
            return Verdict(None, [str(exc)], {"ok": False, "error": str(exc)})
        if sandbox:
            gates = admit_program(program, card)
        else:
            static = check_program(program, card)
            gates = Admission(errors=[with_code(program, v) for v in static.errors],
                              warnings=[str(v) for v in static.warnings])
        record = {"ok": gates.ok, "violations": gates.errors, "warnings": gates.warnings}
        if not gates.ok:
            return Verdict(None, gates.errors, record)
        return Verdict((program, gates.warnings), [], record)

    return judge


def synthesize_program(
    card: TaskCard, backend: LLMBackend, action_dim: int, purpose: Purpose = "lsfs", *, followups: int = 0,
    sandbox: bool = True,
) -> Synthesis:
    """Ask ``backend`` for the task's initial program, sending a refused reply back with its errors up to
    ``followups`` times; raise :class:`SynthesisError` (with every attempt) when none is admissible."""
    dialogue = converse(backend, lsfs_request(card, action_dim, purpose), judge_program(card, sandbox), followups)
    if dialogue.value is None:
        errors = dialogue.attempts[-1].errors if dialogue.attempts else []
        turns = len(dialogue.attempts)
        raise SynthesisError(f"the {purpose.upper()} reply was refused ({turns} attempt{'s' if turns > 1 else ''}); "
                             "the last for: " + "; ".join(errors), attempts=dialogue.attempts)
    program, warnings = dialogue.value
    return Synthesis(program, dialogue.attempts, warnings)
