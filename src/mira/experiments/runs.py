"""One run of a sweep: what to do with it (start, resume, skip, conflict), its state file, and the
``mira train`` subprocess that does it. The sweep itself (:mod:`mira.experiments.sweep`) schedules these.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mira.experiments.grid import RunSpec, task_label
from mira.runio.atomic import atomic_write_json
from mira.runio.rundir import describe_status, stale_reason

STATE_DIR = "_sweep"
USAGE_EXIT = 2  # `mira train` exit status for bad input: retrying cannot help


# ------------------------------------------------------------------------------------ run planning


@dataclass(frozen=True)
class Plan:
    """What a sweep will do with one run now."""

    action: str
    """``skip`` (finished), ``resume``, ``start`` or ``conflict``."""
    reason: str
    overwrite: bool = False


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def plan_run(spec: RunSpec, out: str | Path) -> Plan:
    """Decide from the run directory alone whether ``spec`` is skipped, resumed or started."""
    from mira.runio.checkpoint import list_checkpoints

    run = spec.run_dir(out)
    if not run.exists() or not any(run.iterdir()):
        return Plan("start", "new run")
    saved = read_json(run / "config.json")
    if saved is None or not isinstance(saved.get("config"), dict):
        return Plan("start", "leftover directory without a usable config.json", overwrite=True)
    cfg = saved["config"]
    expected = {"method": spec.method, "algo": spec.algo, "seed": spec.seed}
    for key, want in expected.items():
        if cfg.get(key) != want:
            return Plan("conflict", f"{run} holds a run with {key}={cfg.get(key)!r}, the grid wants "
                                    f"{want!r}; "
                                    "move it away or use another --out")
    have = str(cfg.get("program") or "")
    if (str(Path(have).resolve()) if have else "") != (str(Path(spec.program).resolve()) if spec.program else ""):
        return Plan("conflict", f"{run} holds a run started from {_program_text(have)}, the grid wants "
                                f"{_program_text(spec.program)}; move it away or use another --out")
    if task_label(str(cfg.get("task", ""))) != task_label(spec.task):
        return Plan("conflict", f"{run} holds a run of task {cfg.get('task')!r}, the grid wants "
                                f"{spec.task!r}")
    if not isinstance(cfg.get("steps"), int) or cfg["steps"] > spec.steps:
        return Plan("conflict", f"{run} holds a run with steps={cfg.get('steps')!r}, the grid wants "
                                f"{spec.steps!r}; move it away or use another --out")
    status = read_json(run / "status.json") or {}
    if status.get("status") == "finished" and status.get("step") == spec.steps:
        return Plan("skip", "finished")
    checkpoints = list_checkpoints(run / "checkpoints")
    if checkpoints and cfg["steps"] < spec.steps:
        # A shorter run of the same configuration is extended from its last checkpoint, not started over.
        return Plan("resume", f"extend from {cfg['steps']} to {spec.steps} steps (at step {checkpoints[-1]})")
    if checkpoints:
        return Plan("resume", describe_status(status))
    return Plan("start", f"{stale_reason(status) or status.get('status', 'unknown')} before its first checkpoint",
                overwrite=True)


def _program_text(program: str) -> str:
    return f"program {program}" if program else "the task's own program"


def train_command(spec: RunSpec, out: str | Path, plan: Plan, python: str | None = None) -> list[str]:
    """The ``mira train`` subprocess command line carrying out ``plan``."""
    base = [python or sys.executable, "-m", "mira.cli", "train"]
    run = str(spec.run_dir(out))
    if plan.action == "resume":
        return [*base, "--resume", run, "--steps", str(spec.steps), "--quiet"]
    cmd = [*base, "--task", spec.task, "--method", spec.method, "--algo", spec.algo, "--seed", str(spec.seed),
           "--steps", str(spec.steps), "--out", run]
    if spec.program:
        cmd += ["--program", spec.program]
    if plan.overwrite:
        cmd.append("--overwrite")
    extra = list(spec.train_args)
    if "--quiet" not in extra:
        extra.append("--quiet")
    return cmd + extra


# -------------------------------------------------------------------------------------- run state


def _flat_id(spec: RunSpec) -> str:
    return spec.run_id.replace("/", "__")


def state_path(spec: RunSpec, out: str | Path) -> Path:
    root = Path(out) / STATE_DIR / "state"
    parts = spec.run_id.split("/")
    return root.joinpath(*parts[:-1], f"{parts[-1]}.json")


def log_path(spec: RunSpec, out: str | Path) -> Path:
    return Path(out) / STATE_DIR / "logs" / f"{_flat_id(spec)}.log"


def read_state(spec: RunSpec, out: str | Path) -> dict[str, Any]:
    return read_json(state_path(spec, out)) or {"run": spec.run_id, "state": "pending", "attempts": 0,
                                                   "wall_s": 0.0}


def write_state(spec: RunSpec, out: str | Path, **changes: Any) -> dict[str, Any]:
    """Update a run's state file atomically (read, merge, replace) and return the new state."""
    state = read_state(spec, out)
    state.update(changes)
    state["run"] = spec.run_id
    state["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    atomic_write_json(state_path(spec, out), state)
    return state


def _pid_runs(pid: Any, run_dir: Path) -> bool:
    """True if ``pid`` is a live process on this host whose command line names ``run_dir``."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().decode("utf-8", "replace")
    except (OSError, ValueError):
        return False
    return str(run_dir) in cmdline.split("\0")


def busy_elsewhere(spec: RunSpec, out: str | Path) -> bool:
    """A run still being trained by a process that outlived an earlier sweep, or by a ``mira train``
    started by hand (same host: its ``status.json`` names a live process)."""
    state = read_state(spec, out)
    if (state.get("state") == "running" and state.get("host") == socket.gethostname()
            and _pid_runs(state.get("pid"), spec.run_dir(out))):
        return True
    status = read_json(spec.run_dir(out) / "status.json") or {}
    pid = status.get("pid")
    return (status.get("status") == "running" and status.get("host") == socket.gethostname()
            and isinstance(pid, int) and pid != os.getpid() and stale_reason(status) is None)


# ----------------------------------------------------------------------------------- subprocesses


def _child_setup() -> None:  # pragma: no cover - runs in the forked child
    # Default SIGINT (a shell may have left it ignored) so that the trainer can turn it into an
    # "interrupted" status; and die with the parent so no orphan keeps writing a run directory.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            libc.prctl(1, signal.SIGINT)  # PR_SET_PDEATHSIG
        except OSError:
            pass


def child_env(threads: int | None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    if threads is not None:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env.setdefault(var, str(threads))
    return env


def launch(spec: RunSpec, out: str | Path, plan: Plan, threads: int | None,
           python: str | None = None) -> tuple[subprocess.Popen[bytes], list[str], IO[bytes]]:
    """Start the run's subprocess with its output appended to the run's sweep log."""
    cmd = train_command(spec, out, plan, python)
    log = log_path(spec, out)
    log.parent.mkdir(parents=True, exist_ok=True)
    fh = open(log, "ab")  # noqa: SIM115 - closed by the caller when the process ends
    now = time.strftime("%Y-%m-%dT%H:%M:%S")
    header = f"\n=== {now} {plan.action} ({plan.reason}) on {socket.gethostname()}\n"
    fh.write(header.encode() + (" ".join(cmd) + "\n").encode())
    fh.flush()
    proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            env=child_env(threads), start_new_session=True, preexec_fn=_child_setup)
    return proc, cmd, fh


def _tail(path: Path, lines: int = 5) -> str:
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - 4000))
            text = fh.read().decode("utf-8", "replace")
    except OSError:
        return ""
    return " | ".join(ln.strip() for ln in text.strip().splitlines()[-lines:])


def end_state(spec: RunSpec, out: str | Path, rc: int, wall: float) -> dict[str, Any]:
    previous = read_state(spec, out)
    total = float(previous.get("wall_s") or 0.0) + wall
    if rc == 0:
        return write_state(spec, out, state="finished", returncode=0, last_wall_s=round(wall, 3),
                           wall_s=round(total, 3), ended=time.time(), pid=None, message="")
    kind = "interrupted" if rc in (130, -signal.SIGINT) else "failed"
    message = f"exit status {rc}" if rc >= 0 else f"killed by signal {-rc}"
    return write_state(spec, out, state=kind, returncode=rc, last_wall_s=round(wall, 3),
                       wall_s=round(total, 3),
                       ended=time.time(), pid=None, message=f"{message}; {_tail(log_path(spec, out), 2)}")


class RunFailed(Exception):
    """A run's subprocess exited non-zero (retryable: the next attempt resumes it)."""


class RunRejected(Exception):
    """A run cannot proceed (conflicting directory, or ``mira train`` rejected its input)."""


def execute_run(spec_data: dict[str, Any], out: str, threads: int | None = None,
                backend: str = "ray") -> dict[str, Any]:
    """Plan, run and record one run in the calling process (the body of a Ray task).

    Raises :class:`RunFailed` on a failed attempt (Ray retries it) and :class:`RunRejected` when
    retrying cannot help.
    """
    spec = RunSpec.from_dict(spec_data)
    plan = plan_run(spec, out)
    if plan.action == "skip":
        write_state(spec, out, state="finished", action="skip", pid=None)
        return {"run": spec.run_id, "action": "skip", "returncode": 0, "wall_s": 0.0}
    if plan.action == "conflict":
        write_state(spec, out, state="failed", action="conflict", message=plan.reason, pid=None)
        raise RunRejected(f"{spec.run_id}: {plan.reason}")
    attempts = int(read_state(spec, out).get("attempts") or 0) + 1
    t0 = time.time()
    proc, cmd, fh = launch(spec, out, plan, threads)
    write_state(spec, out, state="running", action=plan.action, attempts=attempts, pid=proc.pid,
                host=socket.gethostname(), backend=backend, started=t0, command=cmd,
                log=str(log_path(spec, out).relative_to(out)))
    try:
        rc = proc.wait()
    except BaseException:  # cancelled (KeyboardInterrupt from Ray): stop the run gently, then firmly
        stop_all([proc])
        rc = proc.wait()
        raise
    finally:
        fh.close()
        end_state(spec, out, proc.returncode if proc.returncode is not None else -9, time.time() - t0)
    if rc == USAGE_EXIT:
        raise RunRejected(f"{spec.run_id}: mira train rejected its input; see {log_path(spec, out)}")
    if rc != 0:
        raise RunFailed(f"{spec.run_id}: exit status {rc}; see {log_path(spec, out)}")
    return {"run": spec.run_id, "action": plan.action, "returncode": 0, "wall_s": time.time() - t0}


def stop_all(procs: list[subprocess.Popen[bytes]], grace_s: float = 180.0) -> None:
    """SIGINT (the trainer records "interrupted"), then SIGKILL whatever is left after ``grace_s``. The grace
    covers what a run finishes before it stops: an evaluation or outer-loop cycle in progress and a checkpoint
    that holds the replay buffer (hundreds of megabytes on the larger tasks); a run killed before that
    resumes from its previous checkpoint, up to a checkpoint interval behind."""
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(signal.SIGINT)
    deadline = time.time() + grace_s
    for p in procs:
        try:
            p.wait(timeout=max(0.0, deadline - time.time()))
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                p.kill()
            p.wait()


