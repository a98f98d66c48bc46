"""The gates every program passes before it is used: static integrity, then the sandbox on real states.

One function for the initial program (an LLM's, the offline engineer's or a ``--program`` file) and for
SRR's candidates, so no program reaches training through a door with fewer checks. The outcome keeps
the errors in the words a model can act on (factor, line, the offending code) and the warnings a
person should see (a constant factor, a range hint the states leave).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mira.factors.checker import check_program
from mira.factors.program import FactorProgram
from mira.factors.sandbox import SandboxLimits, SandboxReport, sandbox_check
from mira.factors.violations import Violation
from mira.tasks.card import TaskCard


@dataclass
class Admission:
    """Whether a program may be used, why not, and what a person should know about it."""

    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    static: dict[str, Any] = field(default_factory=dict)
    sandbox: SandboxReport | None = None

    @property
    def ok(self) -> bool:
        return not self.errors


def with_code(program: FactorProgram, violation: Violation) -> str:
    """A violation followed by the line of code it is about, when it names one."""
    text = str(violation)
    factor = next((f for f in program.factors if f.name == violation.factor), None)
    if factor is not None and violation.line > 0:
        lines = factor.code.splitlines()
        if violation.line <= len(lines):
            text += f"  <- `{lines[violation.line - 1].strip()}`"
    return text


def admit_program(
    program: FactorProgram,
    card: TaskCard,
    *,
    states: np.ndarray | None = None,
    actions: np.ndarray | None = None,
    only: list[str] | None = None,
    timeout_s: float | None = None,
) -> Admission:
    """Static checks of the whole program, then the sandbox on its factors (``only`` those named, when
    given: an edit's unchanged factors were admitted before). ``states``/``actions`` replace the
    sandbox's default random-policy batch."""
    static = check_program(program, card)
    out = Admission(static={"ok": static.ok, "violations": static.lines()})
    out.errors = [with_code(program, v) for v in static.errors]
    out.warnings = [str(v) for v in static.warnings]
    if out.errors:
        return out
    if only is not None and not any(f.name in only for f in program.factors):
        return out  # nothing new to run (a Prune, say): what is left was admitted before
    run = program if only is None else program.with_factors([f for f in program.factors if f.name in only])
    limits = SandboxLimits() if timeout_s is None else SandboxLimits(wall_timeout_s=timeout_s)
    report = sandbox_check(run, card, states=states, actions=actions, limits=limits)
    out.sandbox = report
    out.errors = [with_code(program, v) for v in report.violations]
    if not report.ok and not out.errors:
        out.errors = ["the sandbox refused the program without naming a factor"]
    for name, verdict in report.factors.items():
        out.warnings += [w if w.startswith("warning:") else f"warning: {name}:0: [sandbox] {w}"
                         for w in verdict.warnings]
    return out
