"""How long a sweep would take: steps/s per (task, algo, method), from runs already logged or a short probe.

A run's cost per step depends on the task (simulation), the algorithm and the reward method (HARS's
head and potential, the monitor), and on the machine, so the estimate is measured, never assumed:
the median ``steps_per_s`` that runs under the sweep's directory already logged, and for a
(task, algo, method) none has, a **probe**: a real ``mira train`` of a few thousand steps in a
temporary directory (removed after), timed over the steps after learning has started, with the grid's
own train args. Evaluations are not counted; runs in parallel are assumed to keep their speed (one
intra-op thread each, one run per core).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mira.experiments.grid import RunSpec, task_label

SpeedKey = tuple[str, str, str]

PROBE_WARMUP_STEPS = 2_000
"""Random steps before the probe's timed window: learning has started and, on 1,000-step episodes,
two episodes are done, so HARS's decomposition head is fitting as it would in the run."""
PROBE_MEASURED_STEPS = 500
"""Steps of the probe's timed window (two logged intervals), all with gradient updates."""
PROBE_TIMEOUT_S = 900.0


def speed_key(spec: RunSpec) -> SpeedKey:
    return task_label(spec.task), spec.algo, spec.method


def measured_speeds(out: Path, specs: list[RunSpec]) -> dict[SpeedKey, float]:
    """Median steps/s of each (task, algo, method) over the runs under ``out`` that have logged any."""
    from mira.runio.csvlog import read_csv

    seen: dict[SpeedKey, list[float]] = {}
    for spec in specs:
        log = spec.run_dir(out) / "train.csv"
        if log.is_file():
            rates = [float(r["steps_per_s"]) for r in read_csv(log) if r.get("steps_per_s")]
            seen.setdefault(speed_key(spec), []).extend(r for r in rates if r > 0)
    return {key: float(np.median(v)) for key, v in seen.items() if v}


@dataclass(frozen=True)
class ProbeResult:
    key: SpeedKey
    steps_per_s: float | None
    """None when the probe failed; ``error`` says why."""
    error: str = ""


def probe_command(spec: RunSpec, run_dir: Path, warmup: int, measured: int) -> list[str]:
    """``mira train`` for a probe of ``spec``: the grid's train args, then the probe's budget (which wins)."""
    total = warmup + measured
    half = max(1, measured // 2)
    return [sys.executable, "-m", "mira.cli", "train", "--task", spec.task, "--method", spec.method,
            "--algo", spec.algo, "--seed", str(spec.seed), "--out", str(run_dir),
            *(["--program", spec.program] if spec.program else []), *spec.train_args,
            "--steps", str(total + half), "--learning-starts", str(warmup), "--log-every", str(half),
            "--eval-every", str(total + half), "--eval-episodes", "1", "--checkpoint-every", str(total + half),
            "--quiet"]


def probe_speed(spec: RunSpec, warmup: int = PROBE_WARMUP_STEPS, measured: int = PROBE_MEASURED_STEPS,
                timeout_s: float = PROBE_TIMEOUT_S) -> ProbeResult:
    """Steps/s of ``spec``'s training once learning has started, from a short real run.

    The run goes on ``measured // 2`` steps past the timed window so that the final evaluation falls
    outside it; the figure is the median over the logged intervals that lie wholly after ``warmup``.
    """
    from mira.runio.csvlog import read_csv

    key = speed_key(spec)
    with tempfile.TemporaryDirectory(prefix="mira-probe-") as tmp:
        run_dir = Path(tmp) / "run"
        try:
            proc = subprocess.run(probe_command(spec, run_dir, warmup, measured), capture_output=True,
                                  text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            return ProbeResult(key, None, f"no result within {timeout_s:.0f} s")
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
            return ProbeResult(key, None, last)
        rows = read_csv(run_dir / "train.csv") if (run_dir / "train.csv").is_file() else []
        half = max(1, measured // 2)
        rates = [float(r["steps_per_s"]) for r in rows
                 if r.get("steps_per_s") and warmup + half <= int(r["step"]) <= warmup + measured]
    if not rates:
        return ProbeResult(key, None, "the probe logged no speed")
    return ProbeResult(key, float(np.median(rates)))
