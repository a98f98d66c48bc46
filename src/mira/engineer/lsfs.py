"""Linguistic-Semantic Factor Synthesis (section 4.2.1): the initial factor program of a task.

One entry point for every caller (``mira factors synth``, HARS/MIRA, LaRe): build the structured
prompt from the task card, ask the configured backend (an LLM, a script, or the offline rule-based
engineer — the caller never knows which), parse the reply strictly, and check the program before
anyone uses it. The backend is built from an :class:`~mira.config.LLMConfig` with the response cache
on by default and every exchange audited in the run directory.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from mira.engineer.backends import make_backend
from mira.engineer.lsfs_prompt import build_lsfs_messages, parse_program_reply
from mira.errors import MiraError
from mira.factors.checker import check_program
from mira.factors.program import FactorProgram, ProgramParseError
from mira.llm.base import LLMBackend, LLMRequest
from mira.llm.config import LLMConfig
from mira.tasks.card import TaskCard

Purpose = Literal["lsfs", "srr", "lare"]


class SynthesisError(MiraError):
    """The backend's program could not be parsed or is not admissible."""


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


def synthesize_program(
    card: TaskCard, backend: LLMBackend, action_dim: int, purpose: Purpose = "lsfs"
) -> FactorProgram:
    """Ask ``backend`` for the task's initial program; raise :class:`SynthesisError` unless admissible."""
    reply = backend.complete(lsfs_request(card, action_dim, purpose))
    record = getattr(backend, "record_parse_result", None)
    try:
        program = parse_program_reply(reply.content, card)
    except ProgramParseError as exc:
        if record is not None:
            record(reply, {"ok": False, "error": str(exc)})
        raise SynthesisError(f"the {purpose.upper()} reply is not a usable program: {exc}") from exc
    report = check_program(program, card)
    if record is not None:
        record(reply, {"ok": report.ok, "violations": report.lines()})
    if not report.ok:
        raise SynthesisError(f"the {purpose.upper()} program is not admissible: " + "; ".join(report.lines()))
    return program
