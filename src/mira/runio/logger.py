"""One logger, several sinks: the trainer records a group of scalars at a step once, each sink writes it.

As Stable-Baselines3's logger does with its output formats: the loop says *what* happened (``eval``,
``train``, ``outer`` scalars at a step), and :class:`CsvSink` (one append-only CSV file per group it
knows) and :class:`TensorBoardSink` (a tag ``group/name`` per numeric value) decide how it is kept.
A new sink (another file format, a remote tracker) is one class with ``record``, ``flush`` and
``close``; the loop does not change.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from mira.runio.csvlog import CsvLog, rewind_csv


class Sink(Protocol):
    def record(self, group: str, step: int, values: Mapping[str, Any]) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


class CsvSink:
    """``<run>/<group>.csv`` for each group given a column list; other groups are not its business. On a
    resume, rows after the checkpoint's step are dropped first: they will be written again, identically."""

    def __init__(self, run_dir: Path, columns: Mapping[str, Sequence[str]], resume_step: int) -> None:
        self.logs = {group: CsvLog(Path(run_dir) / f"{group}.csv", fields) for group, fields in columns.items()}
        # Every CSV of the run, the outer loop's included (or, resuming a run killed before its first
        # checkpoint, any row at all).
        for path in sorted(Path(run_dir).glob("*.csv")):
            rewind_csv(path, resume_step)

    def widen(self, group: str, fields: Sequence[str]) -> None:
        """Add columns to a group's file (a new program's factors bring new columns)."""
        self.logs[group].widen(fields)

    def record(self, group: str, step: int, values: Mapping[str, Any]) -> None:
        log = self.logs.get(group)
        if log is not None:
            log.append({"step": step, **values})

    def flush(self) -> None:
        pass  # every row is on disk when append returns

    def close(self) -> None:
        pass


class TensorBoardSink:
    """TensorBoard scalars ``group/name`` for every numeric value (``step`` is the axis, not a scalar).

    ``purge_step`` drops events a killed run logged after its checkpoint (they will be logged again)."""

    def __init__(self, directory: Path, purge_step: int | None,
                 skip: Mapping[str, Sequence[str]] | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(str(directory), purge_step=purge_step, flush_secs=30)
        self.skip = {group: set(names) for group, names in (skip or {}).items()}

    def record(self, group: str, step: int, values: Mapping[str, Any]) -> None:
        skipped = self.skip.get(group, set())
        for name, value in values.items():
            if name != "step" and name not in skipped and isinstance(value, float | int) \
                    and not isinstance(value, bool):
                self.writer.add_scalar(f"{group}/{name}", value, step)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


class RunLogger:
    """Fans each record out to every sink."""

    def __init__(self, sinks: Sequence[Sink]) -> None:
        self.sinks = list(sinks)

    def record(self, group: str, step: int, values: Mapping[str, Any]) -> None:
        for sink in self.sinks:
            sink.record(group, step, values)

    def flush(self) -> None:
        for sink in self.sinks:
            sink.flush()

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()
