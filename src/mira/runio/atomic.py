"""Crash-safe file writes.

Every file MIRA writes into a run directory goes through here, so that a kill at any instant leaves
either the previous complete file or the new complete file, never a torn one: write to a temporary
file in the same directory, flush and fsync it, rename it over the target (atomic on POSIX), then
fsync the directory so the rename itself survives a power cut.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from mira.errors import DiskFullError

# Out of space, over quota, or over the process's file-size limit: all mean "cannot grow a file".
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically (temp file + fsync + rename + directory fsync)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            os.fchmod(handle.fileno(), 0o644)  # mkstemp creates 0600; run files are meant to be shared
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
        _fsync_dir(target.parent)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        if exc.errno in _NO_SPACE:
            raise DiskFullError(f"no space left writing {target}: {exc.strerror}") from exc
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Replace ``path`` with ``text`` (UTF-8) atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Replace ``path`` with ``obj`` as indented JSON atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def append_line(path: str | os.PathLike[str], line: str) -> None:
    """Append one line to an append-only log and fsync it.

    A kill mid-write can leave a torn last line; readers (``read_jsonl``, ``CsvLog.read``) drop it.
    """
    target = Path(path)
    data = (line.rstrip("\n") + "\n").encode("utf-8")
    try:
        with open(target, "ab") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
    except OSError as exc:
        if exc.errno in _NO_SPACE:
            raise DiskFullError(f"no space left appending to {target}: {exc.strerror}") from exc
        raise


def read_jsonl(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Read a JSON Lines log, skipping a torn (unparseable, unterminated) final line."""
    target = Path(path)
    if not target.exists():
        return []
    raw = target.read_text(encoding="utf-8")
    lines = raw.split("\n")
    records: list[dict[str, Any]] = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if i == len(lines) - 1:  # torn last line: the write was interrupted
                break
            raise
    return records
