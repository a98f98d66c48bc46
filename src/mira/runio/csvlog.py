"""Append-only CSV logs that survive kills and can be rewound on resume."""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mira.runio.atomic import append_line, atomic_write_text


def _format(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)
    if value is None:
        return ""
    return str(value)


class CsvLog:
    """A CSV file with a header, written one fsynced row at a time (``widen`` adds columns).

    A kill can tear only the last row; opening the log drops such a fragment. ``rewind(step)`` drops
    rows logged after a checkpoint so that a resumed run appends exactly what an uninterrupted run
    would have written.
    """

    def __init__(self, path: str | os.PathLike[str], fields: Sequence[str]) -> None:
        self.path = Path(path)
        self.fields = list(fields)
        if self.path.exists():
            self._repair()
        else:
            atomic_write_text(self.path, ",".join(self.fields) + "\n")

    def _repair(self) -> None:
        raw = self.path.read_text(encoding="utf-8")
        if not raw:
            atomic_write_text(self.path, ",".join(self.fields) + "\n")
            return
        if not raw.endswith("\n"):
            raw = raw[: raw.rfind("\n") + 1]
            atomic_write_text(self.path, raw)
        header = next(csv.reader([raw.split("\n", 1)[0]]))
        if header != self.fields:
            # A newer version may log more columns; keep the file's own header so rows stay aligned.
            self.fields = header

    def widen(self, fields: Sequence[str]) -> None:
        """Add columns (those not yet in the header), rewriting the file once: earlier rows leave them
        empty. For figures that appear mid-run, such as the factors of a newly installed program."""
        new = [f for f in fields if f not in self.fields]
        if not new:
            return
        rows = self.read()
        self.fields = [*self.fields, *new]
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=self.fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_text(self.path, buf.getvalue())

    def append(self, row: Mapping[str, Any]) -> None:
        buf = io.StringIO()
        csv.writer(buf, lineterminator="").writerow([_format(row.get(k)) for k in self.fields])
        append_line(self.path, buf.getvalue())

    def read(self) -> list[dict[str, str]]:
        return read_csv(self.path)

    def rewind(self, step: int, key: str = "step") -> None:
        """Drop every row whose ``key`` column exceeds ``step``."""
        rows = [r for r in self.read() if r.get(key, "") == "" or int(float(r[key])) <= step]
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=self.fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_text(self.path, buf.getvalue())


def read_csv(path: str | os.PathLike[str]) -> list[dict[str, str]]:
    """Read a CSV log as dictionaries, ignoring a torn final line."""
    target = Path(path)
    if not target.exists():
        return []
    raw = target.read_text(encoding="utf-8")
    if raw and not raw.endswith("\n"):
        raw = raw[: raw.rfind("\n") + 1]
    return list(csv.DictReader(io.StringIO(raw)))


def rewind_csv(path: str | os.PathLike[str], step: int, key: str = "step") -> None:
    """Drop the rows of a CSV log (with its own header) logged after ``step``."""
    raw = Path(path).read_text(encoding="utf-8")
    header = next(csv.reader([raw.split("\n", 1)[0]]), [])
    if key in header:
        CsvLog(path, header).rewind(step, key)
