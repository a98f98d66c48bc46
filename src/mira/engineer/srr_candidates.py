"""Turning an SRR reply into candidate programs, or into clear reasons why not.

A reply must be one JSON object with a ``candidates`` list (code fences and prose around it are
tolerated, as real LLMs send them). Each candidate's ``updated_factors`` is applied to the current
program by name — replacing or adding — and factors named by a ``Prune`` edit are removed, so both a
complete revised factor set and a patch of changed factors are understood. The result is a new
program version whose parent, edits and rationale are recorded. Anything that does not fit the
schema or the factor model is rejected here, before any check runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mira.engineer.replyjson import find_json_object
from mira.factors.program import Factor, FactorProgram, ProgramParseError

ALLOWED_OPERATORS = ("Scale", "Sat", "Gate", "Refactor", "Add", "Prune")


@dataclass
class Candidate:
    index: int
    program: FactorProgram | None
    operators: list[str]
    edits: list[dict[str, Any]]
    error: str | None = None
    verdicts: dict[str, Any] = field(default_factory=dict)

    @property
    def parsed(self) -> bool:
        return self.program is not None

    @property
    def admitted(self) -> bool:
        """Parsed and not refused by the static checks or the sandbox (efficacy is judged after)."""
        return self.program is not None and "rejected" not in self.verdicts


def parse_candidates(text: str, current: FactorProgram, max_candidates: int) -> list[Candidate]:
    """Candidates of an SRR reply; raises ``ProgramParseError`` when the reply as a whole is unusable."""
    obj = find_json_object(text, "candidates")
    raw = obj.get("candidates")
    if not isinstance(raw, list) or not raw:
        raise ProgramParseError("the reply's JSON has no non-empty 'candidates' list")
    out = []
    for i, cand in enumerate(raw[:max_candidates]):
        out.append(_candidate(i, cand, current))
    return out


def _candidate(i: int, raw: Any, current: FactorProgram) -> Candidate:
    where = f"candidate {i}"
    if not isinstance(raw, dict):
        return Candidate(i, None, [], [], f"{where}: expected an object")
    edits = raw.get("edits", [])
    updated = raw.get("updated_factors", [])
    if not isinstance(edits, list) or not isinstance(updated, list):
        return Candidate(i, None, [], [], f"{where}: 'edits' and 'updated_factors' must be lists")
    operators: list[str] = []
    pruned: set[str] = set()
    for j, edit in enumerate(edits):
        if not isinstance(edit, dict) or edit.get("operator") not in ALLOWED_OPERATORS:
            op = edit.get("operator") if isinstance(edit, dict) else edit
            return Candidate(i, None, [], edits, f"{where}, edit {j}: unknown operator {op!r}")
        operators.append(edit["operator"])
        if edit["operator"] == "Prune":
            targets = edit.get("targets", [])
            pruned.update(t for t in targets if isinstance(t, str))
    if not updated and not pruned:
        return Candidate(i, None, operators, edits, f"{where}: changes nothing (no updated_factors, no Prune)")
    factors = {f.name: f for f in current.factors if f.name not in pruned}
    try:
        for j, item in enumerate(updated):
            if not isinstance(item, dict):
                raise ProgramParseError(f"updated_factors[{j}] is not an object")
            item = {"doc": "", "units": "", "range_hint": "", **item}
            factor = Factor.from_json(item, where=f"{where}, updated_factors[{j}]")
            factors[factor.name] = factor
        program = current.with_factors(
            list(factors.values()),
            version=current.version + 1,
            parent_version=current.version,
            edits=tuple(e for e in edits if isinstance(e, dict)),
            rationale="; ".join(str(e.get("justification", "")) for e in edits if isinstance(e, dict)),
        )
    except (ProgramParseError, ValueError, TypeError) as exc:
        return Candidate(i, None, operators, edits, f"{where}: {exc}")
    if program.content_hash() == current.content_hash():
        return Candidate(i, None, operators, edits, f"{where}: identical to the current program")
    return Candidate(i, program, operators, edits)
