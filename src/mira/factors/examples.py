"""The paper's section 5.3 factor programs, shipped as JSON files in ``mira/examples``.

``halfcheetah_f0`` / ``humanoidstandup_f0`` are the initial LSFS programs of the two case studies;
``*_f1`` are the programs after the SRR edit the paper describes (a posture Gate on ``r_vel``; an
added, bounded escape bonus ``r_explore``). Each F1 file is exactly what :func:`apply_edits`
produces from F0 with the recorded edit, so the files double as a worked example of the operators.
The offline reward engineer starts from these.
"""

from __future__ import annotations

import json
from importlib import resources

from mira.errors import UsageError
from mira.factors.program import FactorProgram

_PACKAGE = "mira"
_FOLDER = "examples"


def example_programs() -> list[tuple[str, int]]:
    """(task, version) of every shipped example."""
    found: list[tuple[str, int]] = []
    for entry in resources.files(_PACKAGE).joinpath(_FOLDER).iterdir():
        stem, _, suffix = entry.name.rpartition(".")
        task, sep, ver = stem.rpartition("_f")
        if suffix == "json" and sep and ver.isdigit():
            found.append((task, int(ver)))
    return sorted(found)


def example_program(task: str, version: int = 0) -> FactorProgram:
    """The shipped example program for ``task`` at ``version`` (0 = initial, 1 = after one SRR edit)."""
    name = f"{task}_f{int(version)}.json"
    entry = resources.files(_PACKAGE).joinpath(_FOLDER, name)
    if not entry.is_file():
        have = ", ".join(f"{t} v{v}" for t, v in example_programs())
        raise UsageError(f"no example program for task {task!r} version {version} (have: {have})")
    return FactorProgram.from_json(json.loads(entry.read_text(encoding="utf-8")))
