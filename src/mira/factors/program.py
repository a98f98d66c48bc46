"""Reward-factor programs: typed, documented, versioned factors in the JSON contract of DESIGN.md.

A :class:`FactorProgram` is an immutable value. Every change (an SRR edit) produces a
new program with its own version number, its parent's version, the edits that produced it, the
rationale and the unified diff of the code, so a run directory can replay the whole history.

Construction validates the *schema* (types of fields, identifiers, unique names, PHI/AUX tags, PHI
code that takes or reads the action): these are things no later stage can repair. Whether the code
is admissible is the checker's business (:mod:`mira.factors.checker`), so that a rejected program
still loads and its violations can be reported with rule ids and lines.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import keyword
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.factors.syntax import FACTOR_TYPES, STATE_ONLY_TYPES, reads_action
from mira.factors.violations import Violation
from mira.runio.atomic import atomic_write_json

FACTOR_FIELDS = ("name", "type", "code", "doc", "units", "range_hint", "polarity", "monotonicity")
PROGRAM_FIELDS = ("task", "version", "factors", "parent_version", "edits", "rationale", "diff")
POLARITIES = ("reward", "penalty", "mixed")


class ProgramParseError(UsageError):
    """A factor program (file, JSON object or LLM reply) does not follow the contract."""

    def __init__(self, message: str, violations: Iterable[Violation] = ()) -> None:
        self.violations = list(violations)
        super().__init__(message)


@dataclass(frozen=True)
class Factor:
    """One reward factor: a typed function of the state (PHI) or of state and action (AUX).

    ``polarity`` says whether larger values are good (``reward``), bad (``penalty``) or either
    (``mixed``); ``monotonicity`` is free text such as ``"increasing in x_velocity"``. Both are hints
    for people and prompts; nothing enforces them.
    """

    name: str
    type: str
    code: str
    doc: str = ""
    units: str = ""
    range_hint: str = ""
    polarity: str | None = None
    monotonicity: str | None = None

    def to_json(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "name": self.name,
            "type": self.type,
            "code": self.code,
            "doc": self.doc,
            "units": self.units,
            "range_hint": self.range_hint,
        }
        if self.polarity is not None:
            data["polarity"] = self.polarity
        if self.monotonicity is not None:
            data["monotonicity"] = self.monotonicity
        return data

    @classmethod
    def from_json(cls, data: Any, where: str = "factor") -> Factor:
        """Parse and validate one factor object; raises :class:`ProgramParseError`."""
        if not isinstance(data, Mapping):
            raise ProgramParseError(f"{where}: expected an object, got {type(data).__name__}")
        unknown = sorted(set(data) - set(FACTOR_FIELDS))
        if unknown:
            raise ProgramParseError(f"{where}: unknown field(s) {', '.join(map(repr, unknown))}")
        for key in ("name", "type", "code"):
            if key not in data:
                raise ProgramParseError(f"{where}: missing required field {key!r}")
        values: dict[str, Any] = {}
        for key in FACTOR_FIELDS:
            if key not in data:
                continue
            value = data[key]
            optional = key in ("polarity", "monotonicity")
            if not (isinstance(value, str) or (optional and value is None)):
                raise ProgramParseError(
                    f"{where}: field {key!r} must be a string, got {type(value).__name__}"
                )
            values[key] = value
        factor = cls(**values)
        validate_factor(factor, where)
        return factor


def validate_factor(factor: Factor, where: str | None = None) -> None:
    """Schema-level checks no later stage can repair; raises :class:`ProgramParseError`."""
    at = where or f"factor {factor.name!r}"
    name = factor.name
    if (
        not isinstance(name, str)
        or not name.isidentifier()
        or keyword.iskeyword(name)
        or name.startswith("_")
    ):
        raise ProgramParseError(
            f"{at}: name {name!r} is not a valid identifier (letters, digits, '_'; not starting with '_')",
            [Violation(str(name), "program", 0, "invalid factor name")],
        )
    if factor.type not in FACTOR_TYPES:
        raise ProgramParseError(
            f"{at}: type {factor.type!r} is unknown (use 'PHI', 'AUX' or 'SHAPE')",
            [Violation(name, "program", 0, f"unknown factor type {factor.type!r}")],
        )
    if not isinstance(factor.code, str) or not factor.code.strip():
        raise ProgramParseError(f"{at}: code is empty", [Violation(name, "program", 0, "empty code")])
    if factor.polarity is not None and factor.polarity not in POLARITIES:
        raise ProgramParseError(f"{at}: polarity {factor.polarity!r} is not one of {', '.join(POLARITIES)}")
    if factor.type in STATE_ONLY_TYPES and reads_action(factor.code):
        raise ProgramParseError(
            f"{at}: a {factor.type} factor is state-only but its code takes or reads the action 'a' "
            "(make it AUX, or remove the action)",
            [Violation(name, "phi-action", 0, "PHI factor takes or reads the action")],
        )


def _edit_records(value: Any, where: str) -> tuple[dict[str, Any], ...]:
    if value is None:
        return ()
    if not isinstance(value, list | tuple) or not all(isinstance(e, Mapping) for e in value):
        raise ProgramParseError(f"{where}: 'edits' must be a list of objects")
    return tuple(json.loads(json.dumps(dict(e))) for e in value)


@dataclass(frozen=True)
class FactorProgram:
    """A versioned set of factors for one task.

    ``version`` counts from 0 (the LSFS program); ``parent_version`` is the version it was derived
    from (None for an initial program); ``edits`` are the JSON edit records (Appendix A form) that
    produced it; ``rationale`` the justification; ``diff`` the unified diff of the code against the
    parent.
    """

    task: str
    version: int
    factors: tuple[Factor, ...]
    parent_version: int | None = None
    edits: tuple[dict[str, Any], ...] = field(default=(), compare=True)
    rationale: str = ""
    diff: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.task, str) or not self.task:
            raise ProgramParseError("program: 'task' must be a non-empty string")
        if type(self.version) is not int or self.version < 0:
            raise ProgramParseError(
                f"program: 'version' must be a non-negative integer, got {self.version!r}"
            )
        if self.parent_version is not None and (
            type(self.parent_version) is not int or self.parent_version < 0
        ):
            raise ProgramParseError("program: 'parent_version' must be a non-negative integer or null")
        object.__setattr__(self, "factors", tuple(self.factors))
        seen: set[str] = set()
        for factor in self.factors:
            if not isinstance(factor, Factor):
                raise ProgramParseError("program: factors must be Factor objects")
            validate_factor(factor)
            if factor.name in seen:
                raise ProgramParseError(
                    f"program: duplicate factor name {factor.name!r}",
                    [Violation(factor.name, "program", 0, "duplicate factor name")],
                )
            seen.add(factor.name)
        if not self.factors:
            raise ProgramParseError("program: it has no factors")

    def __hash__(self) -> int:  # edits hold dicts; hash what identifies a version
        return hash((self.task, self.version, self.content_hash()))

    # -- views
    @property
    def phi_factors(self) -> tuple[Factor, ...]:
        """State-only factors: the inputs of the potential Φ(s)."""
        return tuple(f for f in self.factors if f.type == "PHI")

    @property
    def aux_factors(self) -> tuple[Factor, ...]:
        """State-action factors: policy-side regularisers, never part of Φ or the shaping term."""
        return tuple(f for f in self.factors if f.type == "AUX")

    @property
    def shape_factors(self) -> tuple[Factor, ...]:
        """Shaping terms: their sum is a potential Ψ(s) added to the agent's reward as γΨ(s′) − Ψ(s),
        outside the decomposition head and Φ."""
        return tuple(f for f in self.factors if f.type == "SHAPE")

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.factors]

    def factor(self, name: str) -> Factor:
        for f in self.factors:
            if f.name == name:
                return f
        raise KeyError(name)

    def content_hash(self) -> str:
        """SHA-256 of the task and the factors (code and metadata), independent of version history.

        Two programs with the same factors hash alike whatever their version numbers, so a run can
        tell that an edit restored an earlier set of factors.
        """
        payload = {"task": self.task, "factors": [f.to_json() for f in self.factors]}
        text = json.dumps(payload, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    def with_factors(self, factors: Iterable[Factor], **changes: Any) -> FactorProgram:
        return replace(self, factors=tuple(factors), **changes)

    # -- JSON
    def to_json(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "task": self.task,
            "version": self.version,
            "factors": [f.to_json() for f in self.factors],
        }
        if self.parent_version is not None:
            data["parent_version"] = self.parent_version
        if self.edits:
            data["edits"] = [dict(e) for e in self.edits]
        if self.rationale:
            data["rationale"] = self.rationale
        if self.diff:
            data["diff"] = self.diff
        return data

    @classmethod
    def from_json(cls, data: Any) -> FactorProgram:
        """Parse and validate a program object; raises :class:`ProgramParseError`."""
        if not isinstance(data, Mapping):
            raise ProgramParseError(f"program: expected a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - set(PROGRAM_FIELDS))
        if unknown:
            raise ProgramParseError(f"program: unknown field(s) {', '.join(map(repr, unknown))}")
        for key in ("task", "version", "factors"):
            if key not in data:
                raise ProgramParseError(f"program: missing required field {key!r}")
        raw = data["factors"]
        if not isinstance(raw, list):
            raise ProgramParseError("program: 'factors' must be a list")
        factors = tuple(Factor.from_json(f, f"factors[{i}]") for i, f in enumerate(raw))
        for key in ("rationale", "diff"):
            if key in data and not isinstance(data[key], str):
                raise ProgramParseError(f"program: {key!r} must be a string")
        return cls(
            task=data["task"],
            version=data["version"],
            factors=factors,
            parent_version=data.get("parent_version"),
            edits=_edit_records(data.get("edits"), "program"),
            rationale=data.get("rationale", ""),
            diff=data.get("diff", ""),
        )

    def save(self, path: str | os.PathLike[str]) -> None:
        """Same as :func:`save_program`."""
        save_program(self, path)

    def to_text(self) -> str:
        """Code of every factor with its metadata as comments (the form diffs are taken of)."""
        parts: list[str] = []
        for f in self.factors:
            parts.append(f"# {f.name} [{f.type}] units={f.units} range={f.range_hint}")
            if f.doc:
                parts.append(f"# {f.doc}")
            parts.append(f.code.rstrip("\n"))
            parts.append("")
        return "\n".join(parts)


def code_diff(old: FactorProgram, new: FactorProgram) -> str:
    """Unified diff of two programs' code and metadata ("" when identical)."""
    lines = difflib.unified_diff(
        old.to_text().splitlines(keepends=True),
        new.to_text().splitlines(keepends=True),
        fromfile=f"{old.task} v{old.version}",
        tofile=f"{new.task} v{new.version}",
    )
    return "".join(lines)


def load_program(path: str | os.PathLike[str]) -> FactorProgram:
    """Read a program JSON file; missing file or invalid JSON is a :class:`UsageError`."""
    target = Path(path)
    try:
        text = target.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UsageError(f"program file {target}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"program file {target}: cannot read it ({exc})") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UsageError(f"program file {target}: invalid JSON ({exc.msg} at line {exc.lineno})") from exc
    return FactorProgram.from_json(data)


def save_program(program: FactorProgram, path: str | os.PathLike[str]) -> None:
    """Write a program as JSON atomically (a crash leaves the old file or the new one, never half)."""
    atomic_write_json(path, program.to_json())
