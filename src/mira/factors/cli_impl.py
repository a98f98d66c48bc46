"""What ``mira factors check`` and ``mira factors synth`` run (the command line only wires flags).

Exit codes of :func:`check_program_file`: 0 admissible; 1 not admissible, with one line per
violation on stdout (``factor:line: [rule] message``); a :class:`UsageError` (exit 2 at the command
line) when the file is missing or is not JSON, or the task is unknown. A program whose JSON is
well-formed but breaks the contract (unknown type, duplicate names, PHI reading the action) is
"not admissible", not a usage error: it is reported with rule ids like any other violation.
"""

from __future__ import annotations

import os
import sys
from typing import TextIO

from mira.factors.checker import check_program
from mira.factors.program import ProgramParseError, load_program
from mira.factors.sandbox import SandboxLimits, sandbox_check
from mira.factors.violations import Violation


def check_program_file(
    path: str | os.PathLike[str],
    task: str,
    *,
    sandbox: bool = True,
    limits: SandboxLimits | None = None,
    out: TextIO | None = None,
) -> int:
    """Static and sandbox checks of a program file against a task; see the module docstring."""
    from mira.tasks import load_task

    stream = out if out is not None else sys.stdout
    card = load_task(task)
    try:
        program = load_program(path)
    except ProgramParseError as exc:
        for v in exc.violations or [Violation("<program>", "program", 0, str(exc))]:
            print(f"{v}" if str(exc) in v.message else f"{v} ({exc})", file=stream)
        return 1
    problems: list[Violation] = []
    if program.task != card.name:
        problems.append(
            Violation(
                "<program>",
                "program",
                0,
                f"the program is for task {program.task!r}, checked against {card.name!r}",
            )
        )
    static = check_program(program, card)
    for v in [*problems, *static.violations]:
        print(str(v), file=stream)
    if problems or not static.ok:
        return 1
    if sandbox:
        report = sandbox_check(program, card, limits=limits)
        for v in report.violations:
            print(str(v), file=stream)
        for name, verdict in report.factors.items():
            for warning in verdict.warnings:
                if not warning.startswith("warning:"):
                    print(f"warning: {name}:0: [sandbox] {warning}", file=stream)
        if not report.ok:
            return 1
        print(
            f"ok: {len(program.factors)} factor(s) admissible for {card.name} "
            f"({len(program.phi_factors)} PHI, {len(program.aux_factors)} AUX"
            + (f", {len(program.shape_factors)} SHAPE" if program.shape_factors else "") + "); sandbox on "
            f"{report.batch_size} real states in {report.wall_seconds:.1f} s",
            file=stream,
        )
    else:
        print(f"ok: {len(program.factors)} factor(s) pass the static checks (sandbox skipped)", file=stream)
    return 0
