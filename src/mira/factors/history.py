"""A run's program versions: every version kept, the current one, exact rollback, saved as files.

``programs/`` of a run directory holds one JSON file per version (``program_vNNN.json``, with the
accepted diff beside it) and ``history.json`` (the current version and the commits and rollbacks in
order); :meth:`ProgramHistory.load` rebuilds the history from them on resume or for ``mira explain``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.factors.edits import Edit, EditError, apply_edits
from mira.factors.program import FactorProgram, load_program, save_program
from mira.runio.atomic import atomic_write_json, atomic_write_text


class ProgramHistory:
    """Every version of a run's factor program, the current one, and exact rollback.

    Versions are never overwritten: rolling back makes an earlier version current again (the very
    same object), and the next edit gets a fresh number (one past the highest), with the restored
    version as its parent. ``events`` records commits and rollbacks in order.
    """

    def __init__(self, initial: FactorProgram) -> None:
        self._versions: dict[int, FactorProgram] = {initial.version: initial}
        self._current = initial.version
        self.events: list[dict[str, Any]] = [{"event": "commit", "version": initial.version}]

    @property
    def current(self) -> FactorProgram:
        return self._versions[self._current]

    @property
    def versions(self) -> list[int]:
        return sorted(self._versions)

    def get(self, version: int) -> FactorProgram:
        try:
            return self._versions[version]
        except KeyError:
            raise EditError(f"no program version {version} (have {self.versions})") from None

    def __len__(self) -> int:
        return len(self._versions)

    def next_version(self) -> int:
        return max(self._versions) + 1

    def commit(self, program: FactorProgram) -> FactorProgram:
        """Record a new version (its number must be unused) and make it current."""
        if program.version in self._versions:
            raise EditError(f"version {program.version} already exists")
        if program.task != self.current.task:
            raise EditError(f"program is for task {program.task!r}, the history for {self.current.task!r}")
        self._versions[program.version] = program
        self._current = program.version
        self.events.append({"event": "commit", "version": program.version, "parent": program.parent_version})
        return program

    def apply(self, edits: Iterable[Edit | Mapping[str, Any]], **kwargs: Any) -> FactorProgram:
        """Apply edits to the current version and commit the result."""
        new = apply_edits(self.current, edits, new_version=self.next_version(), **kwargs)
        return self.commit(new)

    def rollback(self, version: int) -> FactorProgram:
        """Make an earlier version current again, exactly as it was."""
        program = self.get(version)
        self.events.append({"event": "rollback", "version": version, "from": self._current})
        self._current = version
        return program

    # -- persistence: one JSON file per version plus an index
    def save(self, directory: str | os.PathLike[str]) -> None:
        root = Path(directory)
        root.mkdir(parents=True, exist_ok=True)
        for version, program in self._versions.items():
            path = root / f"program_v{version:03d}.json"
            if not path.exists():
                save_program(program, path)
                if program.diff:
                    atomic_write_text(root / f"program_v{version:03d}.diff", program.diff)
        atomic_write_json(
            root / "history.json",
            {"current": self._current, "versions": self.versions, "events": self.events},
        )

    @classmethod
    def load(cls, directory: str | os.PathLike[str]) -> ProgramHistory:
        root = Path(directory)
        try:
            index = json.loads((root / "history.json").read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise UsageError(f"program history {root}: cannot read history.json ({exc})") from exc
        versions = [load_program(root / f"program_v{v:03d}.json") for v in index["versions"]]
        history = cls(versions[0])
        for program in versions[1:]:
            history._versions[program.version] = program
        history._current = int(index["current"])
        history.events = list(index.get("events", []))
        return history
