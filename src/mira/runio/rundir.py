"""The layout of a run directory and its writers.

::

    RUN_DIR/
      config.json        resolved TrainConfig + task card + versions (enough to rerun)
      status.json        running / finished / failed / interrupted, with the last step and message, the
                         process writing it (pid, host) and its heartbeat
      policy.pt          the policy at the latest evaluation (the final one at the end); policy_best.pt:
                         at the best evaluation (mira.agents.policy_file)
      eval.csv           step, return mean/std, episode length, wall seconds
      train.csv          losses, entropy / temperature, steps/s, reward-source scalars
      tb/                TensorBoard scalars
      checkpoints/       verified checkpoints (ckpt-<step>.pt + .json manifest)
      programs/          factor-program versions and diffs (methods with programs)
      diagnostics.csv    MCM, one row per cycle (MIRA methods)
      interventions/     one folder per SRR intervention (MIRA)
      llm/               every LLM exchange and the response cache
"""

from __future__ import annotations

import os
import shutil
import socket
import time
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.runio.atomic import atomic_write_json

EVAL_FIELDS = ("step", "return_mean", "return_std", "length_mean", "episodes", "wall_s")


def prepare_run_dir(out: str | os.PathLike[str], *, resume: bool, overwrite: bool) -> Path:
    """Create (or reopen for resume) a run directory, refusing to clobber an existing run."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {path}: exists and is not a directory")
    if resume:
        if not (path / "config.json").is_file():
            raise UsageError(f"--resume {path}: not a run directory (no config.json)")
        return path
    if path.exists() and any(path.iterdir()):
        if not overwrite:
            raise UsageError(f"--out {path}: directory exists and is not empty (use --resume or --overwrite)")
        shutil.rmtree(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UsageError(f"--out {path}: cannot write there ({exc.strerror})") from exc
    return path


class RunDir:
    """Paths and writers of one run."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.checkpoints = path / "checkpoints"
        self.programs = path / "programs"
        self.interventions = path / "interventions"
        self.llm = path / "llm"

    def write_config(self, data: dict[str, Any]) -> None:
        atomic_write_json(self.path / "config.json", data)

    def set_status(self, status: str, step: int, message: str = "", **progress: Any) -> None:
        """``status.json``: the run's state and step, and while it runs its progress figures (steps/s,
        the last evaluation, the program version), rewritten atomically at every log interval. It names
        the process writing it (``pid``, ``pid_start``, ``host``) and when (``heartbeat``, Unix seconds),
        so that a "running" status left by a killed process is recognised (:func:`stale_reason`)."""
        atomic_write_json(
            self.path / "status.json",
            {"status": status, "step": step, "message": message, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
             **progress, **process_identity(), "heartbeat": round(time.time(), 3)},
        )


def _start_time(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks since boot, from ``/proc``), or None where there is no
    ``/proc`` or no such process: with the pid, it tells a process from a later one given the same pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8")
        return int(stat[stat.rindex(")") + 2:].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def process_identity() -> dict[str, Any]:
    """``pid``, ``pid_start`` and ``host`` of this process, as ``status.json`` records them."""
    pid = os.getpid()
    return {"pid": pid, "pid_start": _start_time(pid), "host": socket.gethostname()}


def stale_reason(status: dict[str, Any]) -> str | None:
    """Why a ``status.json`` that says "running" is not true any more: its process, on this host, is
    gone (killed, or the machine restarted); None when it may still run, when it is not "running", or
    when it cannot be told (another host, or a status written before it named its process)."""
    if status.get("status") != "running":
        return None
    pid = status.get("pid")
    if not isinstance(pid, int) or pid <= 0 or status.get("host") != socket.gethostname():
        return None
    try:
        os.kill(pid, 0)
        alive = True
    except ProcessLookupError:
        alive = False
    except PermissionError:  # someone else's process: it exists
        alive = True
    if alive and status.get("pid_start") is not None and _start_time(pid) not in (None, status["pid_start"]):
        alive = False  # the pid now belongs to a later process
    if alive:
        return None
    beat = status.get("heartbeat")
    when = "" if not isinstance(beat, int | float) else \
        f", last heard of {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(beat))}"
    return f"stopped without a word (killed?): its process {pid} is gone{when}"


def describe_status(status: dict[str, Any]) -> str:
    """``running at step 800``, ``finished at step 3000``, or for a stale "running" status
    ``stopped without a word (killed?) ... at step 800``."""
    state = str(status.get("status", "unknown"))
    stale = stale_reason(status)
    return f"{stale if stale else state} at step {status.get('step', '?')}"
