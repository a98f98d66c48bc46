"""The sandbox's worker processes, driven from the parent: start, feed, read, time out, kill, restart.

A worker (:mod:`mira.factors._worker`, started as ``python -I``) evaluates the factors it is sent under
limits it sets on itself before reading any code; the parent enforces the wall-clock deadlines, kills a
worker's whole process group, restarts a worker that died on one factor for the remaining ones while
time is left, and validates every line a worker writes (JSON with base64 float64 arrays, never
unpickled). What the outputs mean is decided in :mod:`mira.factors.sandbox`.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import math
import os
import pickle
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

_MAX_LINE = 32 * 1024 * 1024
_MAX_STDERR = 16 * 1024
_BOOT = "import sys; sys.path.insert(0, sys.argv[1]); from mira.factors._worker import main; main()"


@dataclass(frozen=True)
class SandboxLimits:
    """Resources a sandbox check may use, whatever the program does."""

    wall_timeout_s: float = 15.0  # the whole check, worker restarts included
    per_factor_timeout_s: float = 4.0
    startup_timeout_s: float = 8.0
    cpu_s: int = 15
    memory_mb: int = 1024  # address space the worker may add to its own start-up size




@dataclass
class WorkerRun:
    results: dict[str, dict[str, Any]] = field(default_factory=dict)
    isolation: list[str] = field(default_factory=list)
    starts: int = 0


def _src_root() -> str:
    import mira

    return str(Path(mira.__file__).resolve().parent.parent)


def _worker_env() -> dict[str, str]:
    env = {"PATH": "/usr/bin:/bin", "LANG": "C.UTF-8"}
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        env[var] = "1"
    return env


def _pump_lines(stream: IO[bytes], out: queue.Queue[bytes | None]) -> None:
    try:
        while True:
            line = stream.readline(_MAX_LINE)
            if not line:
                break
            out.put(line)
    except (OSError, ValueError):
        pass
    finally:
        out.put(None)


def _pump_stderr(stream: IO[bytes], sink: bytearray) -> None:
    try:
        while chunk := stream.read(4096):
            if len(sink) < _MAX_STDERR:
                sink.extend(chunk[: _MAX_STDERR - len(sink)])
    except (OSError, ValueError):
        pass


def _feed(stream: IO[bytes], data: bytes) -> None:
    try:
        stream.write(data)
        stream.close()
    except (OSError, ValueError):
        pass


def _kill(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            proc.kill()
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=5)


def _signal_text(returncode: int | None) -> str:
    if returncode is None:
        return "still running"
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exited with status {returncode}"


def run_workers(
    specs: list[dict[str, str]], job: dict[str, Any], limits: SandboxLimits, deadline: float
) -> WorkerRun:
    run = WorkerRun()
    pending = list(specs)
    while pending and time.monotonic() < deadline - 0.5:
        run.starts += 1
        _one_worker(pending, job, limits, deadline, run)
    for spec in pending:
        run.results[spec["name"]] = {
            "status": "not-run",
            "error": "the sandbox time budget ran out before it ran",
        }
    return run


def _one_worker(
    pending: list[dict[str, str]],
    job: dict[str, Any],
    limits: SandboxLimits,
    deadline: float,
    run: WorkerRun,
) -> None:
    """Start one worker for the pending factors; remove from ``pending`` each factor it settles."""
    jail = tempfile.mkdtemp(prefix="mira-sandbox-")
    payload = pickle.dumps({**job, "factors": list(pending)}, protocol=pickle.HIGHEST_PROTOCOL)
    try:
        proc = subprocess.Popen(
            [sys.executable, "-I", "-c", _BOOT, _src_root()],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            cwd=jail,
            env=_worker_env(),
            close_fds=True,  # the worker inherits no descriptor but its three pipes
            start_new_session=True,  # its own process group, killed as a whole
        )
    except OSError:
        shutil.rmtree(jail, ignore_errors=True)
        raise
    assert proc.stdin is not None and proc.stdout is not None and proc.stderr is not None
    lines: queue.Queue[bytes | None] = queue.Queue()
    stderr = bytearray()
    threads = [
        threading.Thread(target=_feed, args=(proc.stdin, payload), daemon=True),
        threading.Thread(target=_pump_lines, args=(proc.stdout, lines), daemon=True),
        threading.Thread(target=_pump_stderr, args=(proc.stderr, stderr), daemon=True),
    ]
    for t in threads:
        t.start()
    current: str | None = None
    until = min(deadline, time.monotonic() + limits.startup_timeout_s)

    def settle(name: str, record: dict[str, Any]) -> None:
        run.results[name] = record
        pending[:] = [s for s in pending if s["name"] != name]

    try:
        while True:
            try:
                raw = lines.get(timeout=max(0.0, until - time.monotonic()))
            except queue.Empty:
                if current is not None:
                    settle(
                        current,
                        {
                            "status": "timeout",
                            "error": "no result within the time limit "
                            f"({limits.per_factor_timeout_s:g} s per factor); worker killed",
                        },
                    )
                else:
                    for spec in list(pending):
                        settle(spec["name"], {"status": "crash", "error": "the worker did not start in time"})
                return
            if raw is None:  # the worker's stdout closed: it exited or died
                _kill(proc)
                why = _signal_text(proc.returncode)
                tail = stderr.decode("utf-8", "replace").strip().splitlines()[-3:]
                text = f"worker {why}" + (f": {' | '.join(tail)}" if tail else "")
                if current is not None:
                    status = "timeout" if proc.returncode in (-signal.SIGXCPU, -signal.SIGKILL) else "crash"
                    settle(current, {"status": status, "error": text})
                elif pending:
                    for spec in list(pending):
                        settle(spec["name"], {"status": "crash", "error": text})
                return
            msg = _parse_message(raw)
            event = msg.get("event") if msg is not None else None
            if event == "ready":
                iso = msg.get("isolation") if msg else None
                if isinstance(iso, list):
                    run.isolation = [str(x)[:60] for x in iso[:20]]
            elif (
                event == "start"
                and msg is not None
                and msg.get("factor") == (pending[0]["name"] if pending else None)
            ):
                current = pending[0]["name"]
                until = min(deadline, time.monotonic() + limits.per_factor_timeout_s)
            elif (
                event == "result" and msg is not None and current is not None and msg.get("factor") == current
            ):
                settle(current, msg)
                current = None
                until = min(deadline, time.monotonic() + limits.per_factor_timeout_s)
            elif event == "done":
                return
            else:  # anything else is a protocol violation: trust nothing more from this worker
                if current is not None:
                    settle(current, {"status": "crash", "error": "the worker wrote something unexpected"})
                elif pending:
                    for spec in list(pending):
                        settle(
                            spec["name"],
                            {"status": "crash", "error": "the worker wrote something unexpected"},
                        )
                return
    finally:
        _kill(proc)
        for t in threads:
            t.join(timeout=2)
        shutil.rmtree(jail, ignore_errors=True)


def _parse_message(raw: bytes) -> dict[str, Any] | None:
    try:
        msg = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        return None
    return msg if isinstance(msg, dict) else None


def decode_output(record: Any) -> tuple[tuple[int, ...], np.ndarray | None] | None:
    """(shape, float64 values or None) from a worker record; None when the record is malformed."""
    if not isinstance(record, dict):
        return None
    shape = record.get("shape")
    if not isinstance(shape, list) or len(shape) > 32 or not all(type(n) is int and n >= 0 for n in shape):
        return None
    data = record.get("data")
    if data is None:
        return tuple(shape), None
    if not isinstance(data, str):
        return None
    try:
        raw = base64.b64decode(data.encode("ascii"), validate=True)
    except (binascii.Error, UnicodeEncodeError, ValueError):
        return None
    size = math.prod(shape)
    if len(raw) != 8 * size:
        return None
    return tuple(shape), np.frombuffer(raw, dtype="<f8").reshape(shape).copy()
