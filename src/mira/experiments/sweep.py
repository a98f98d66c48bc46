"""Run a sweep grid as independent ``mira train`` runs, locally or on Ray, resumably.

Layout of a sweep output directory ``OUT``::

    OUT/sweep.json                              the manifest: the grid(s) and every run id
    OUT/<task>/<algo>/<method>/seed<k>/         a normal run directory (config.json, eval.csv, tb/ ...)
    OUT/_sweep/state/<task>/<algo>/<method>/seed<k>.json   per-run sweep state (atomic writes)
    OUT/_sweep/logs/<task>__<algo>__<method>__seed<k>.log   the run's stdout/stderr, all attempts
    OUT/_sweep/lock                             held while a sweep drives OUT

Each run is a **subprocess** ``python -m mira.cli train ...``: killing it kills only that run. What to
do with a run is decided from its run directory when it is launched, so a rerun of the same sweep
command picks up where the last one stopped:

- ``status.json`` says finished at step N → **skip** (nothing is touched);
- a verified checkpoint exists → **resume** (``mira train --resume DIR``);
- otherwise → **start** (``--overwrite`` if a directory without a checkpoint is left over);
- a run directory whose config disagrees with the grid (task, method, algo, seed, steps) is a
  **conflict**: it is reported and left alone.

A failed attempt is retried (resumed) up to ``retries`` times within one sweep; exit status 2
(bad input to ``mira train``) is never retried.

Backends: ``pool`` (default) keeps ``workers`` subprocesses running from the main thread; ``ray``
submits each run as a Ray task (``num_cpus=cpus_per_run``) that runs the same subprocess on whichever
node Ray schedules it; Ray's own ``max_retries``/``retry_exceptions`` retries it. With a multi-node
cluster ``OUT`` must be on a filesystem every node sees.

All runs log TensorBoard scalars into their own ``tb/`` under ``OUT``, so
``tensorboard --logdir OUT`` shows every run of the sweep side by side.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mira.errors import UsageError
from mira.experiments.estimate import (
    PROBE_MEASURED_STEPS,
    PROBE_WARMUP_STEPS,
    SpeedKey,
    measured_speeds,
    probe_speed,
    speed_key,
)
from mira.experiments.grid import RunSpec, SweepGrid
from mira.experiments.runs import (
    STATE_DIR,
    USAGE_EXIT,
    Plan,
    RunFailed,
    RunRejected,
    busy_elsewhere,
    end_state,
    execute_run,
    launch,
    log_path,
    plan_run,
    read_json,
    read_state,
    stop_all,
    train_command,
    write_state,
)
from mira.runio.atomic import atomic_write_json

MANIFEST = "sweep.json"

# ------------------------------------------------------------------------------------- progress


@dataclass
class SweepOptions:
    """How a sweep is executed (not what it runs)."""

    workers: int | None = None
    """Local pool: runs in parallel (default 1). Ray without ``address``: start the local instance
    with ``workers × cpus_per_run`` CPUs (default: all of them)."""
    backend: str = "pool"
    """``pool`` or ``ray``."""
    address: str | None = None
    """Ray cluster address (``auto``, ``ray://host:10001``); None starts or reuses a local instance."""
    cpus_per_run: float = 1.0
    """Ray: CPUs reserved per run task (Ray schedules with this resource)."""
    retries: int = 1
    """Re-attempts (resumes) of a failed run within one sweep."""
    threads: int | None = None
    """OMP/MKL threads per run (default: CPU count / workers for the pool, cpus_per_run for Ray)."""
    progress_every_s: float = 30.0
    """Print a progress line at least this often (and whenever a run starts or ends)."""
    stream: IO[str] | None = None
    """Where progress lines go (default ``sys.stdout``)."""
    tqdm: bool | None = None
    """Show a tqdm bar (default: when the stream is a TTY)."""


class Progress:
    """Sweep-level progress: done / running / failed / pending and an ETA from completed wall times."""

    def __init__(self, total: int, slots: int, options: SweepOptions) -> None:
        self.total = total
        self.slots = max(1, slots)
        self.stream = options.stream or sys.stdout
        self.every = options.progress_every_s
        use_tqdm = options.tqdm if options.tqdm is not None else _isatty(self.stream)
        self.bar: Any = None
        if use_tqdm:
            from tqdm import tqdm

            # tqdm's own rate/ETA would count skipped runs as instant: show ours in the postfix instead.
            self.bar = tqdm(total=total, unit="run", file=self.stream, dynamic_ncols=True, desc="sweep",
                            bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]")
        self.walls: list[float] = []
        self._last_line = 0.0
        self._last_key: tuple[int, ...] = ()
        self._shown_done = 0

    def event(self, text: str) -> None:
        line = f"sweep: {text}"
        if self.bar is not None:
            self.bar.write(line, file=self.stream)
        else:
            print(line, file=self.stream, flush=True)

    def eta_s(self, pending: int, running_elapsed: list[float]) -> float | None:
        """Seconds until every run is done if each takes the mean wall time of completed runs:
        running runs finish their remainder, pending ones go to whichever slot frees up first."""
        if not self.walls:
            return None
        mean = sum(self.walls) / len(self.walls)
        slots = sorted(max(0.0, mean - e) for e in running_elapsed)[: self.slots]
        slots += [0.0] * (self.slots - len(slots))
        for _ in range(pending):
            slots.sort()
            slots[0] += mean
        return max(slots)

    def update(self, done: int, skipped: int, failed: int, pending: int, running_elapsed: list[float],
               force: bool = False) -> None:
        key = (done, failed, pending, len(running_elapsed))
        now = time.time()
        eta = self.eta_s(pending, running_elapsed)
        eta_text = "?" if eta is None else _hms(eta)
        text = (f"{done}/{self.total} done ({skipped} skipped), {len(running_elapsed)} running, "
                f"{failed} failed, {pending} pending; ETA {eta_text}")
        if self.bar is not None:
            self.bar.update(done + failed - self._shown_done)
            self._shown_done = done + failed
            self.bar.set_postfix_str(f"{len(running_elapsed)} running, {failed} failed, ETA {eta_text}")
        if force or key != self._last_key or now - self._last_line >= self.every:
            self.event(text)
            self._last_line, self._last_key = now, key

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _isatty(stream: IO[str]) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def _hms(seconds: float) -> str:
    s = round(seconds)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


# ----------------------------------------------------------------------------------------- sweep


@dataclass
class SweepResult:
    out: Path
    total: int
    finished: list[str] = field(default_factory=list)
    """Runs that finished in this sweep."""
    skipped: list[str] = field(default_factory=list)
    """Runs already finished before this sweep (untouched)."""
    failed: dict[str, str] = field(default_factory=dict)
    """Run id → reason, for runs that failed (after retries) or conflict with their directory."""
    busy: list[str] = field(default_factory=list)
    """Runs left alone because a process from an earlier sweep is still training them."""
    interrupted: bool = False
    wall_s: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.failed and not self.busy and not self.interrupted


def write_manifest(grid: SweepGrid, out: Path, options: SweepOptions) -> None:
    """Write ``OUT/sweep.json``: every grid swept into OUT and the union of their run ids.

    A different ``steps`` or ``train_args`` than an earlier grid in the same OUT is refused: the run
    directories would no longer describe one experiment.
    """
    from mira.version import __version__

    path = out / MANIFEST
    old = read_json(path) or {}
    grids = [g for g in old.get("grids", []) if isinstance(g, dict)]
    new = grid.to_dict()
    for g in grids:
        if g.get("steps") != new["steps"] or g.get("train_args") != new["train_args"]:
            raise UsageError(f"{path} was swept with steps={g.get('steps')} and train args "
                             f"{g.get('train_args')}; this grid has steps={new['steps']} and "
                             f"{new['train_args']} "
                             "(use another --out)")
    if new not in grids:
        grids.append(new)
    runs = list(dict.fromkeys([*old.get("runs", []), *(r.run_id for r in grid.runs())]))
    atomic_write_json(path, {"mira": __version__, "grid": new, "grids": grids, "runs": runs,
                             "backend": options.backend, "updated": time.strftime("%Y-%m-%dT%H:%M:%S"),
                             "tensorboard": f"tensorboard --logdir {out}"})


@contextlib.contextmanager
def _sweep_lock(out: Path) -> Iterator[None]:
    import fcntl

    path = out / STATE_DIR / "lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "a+")  # noqa: SIM115
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = fh.read().strip() or "?"
            raise UsageError(f"another sweep is driving {out} (pid {holder})") from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        yield
    finally:
        fh.close()


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def dry_run(grid: SweepGrid, out: str | Path, stream: IO[str] | None = None,
            workers: int | None = None, probe: bool = False) -> list[tuple[RunSpec, Plan]]:
    """Print (and return) what a sweep would do with each run, and how long it would take.

    The speed of each (task, algo, method) is what the runs already under ``out`` logged; with
    ``probe``, one the runs here have not logged is measured by a short real run in a temporary
    directory (:mod:`mira.experiments.estimate`). Writes nothing under ``out``.
    """
    stream = stream or sys.stdout
    out = Path(out)
    if "--preset" in grid.train_args:  # say once what the preset sets in every run below
        from mira.config import PRESETS

        name = grid.train_args[grid.train_args.index("--preset") + 1]
        print(f"every run: mira train --preset {name} = --set {' --set '.join(PRESETS.get(name, ()))}",
              file=stream)
    plans = [(spec, plan_run(spec, out)) for spec in grid.runs()]
    for spec, plan in plans:
        cmd = "" if plan.action in ("skip", "conflict") else "  $ " + " ".join(train_command(spec, out, plan))
        print(f"{plan.action:8s} {spec.run_id}  ({plan.reason}){cmd}", file=stream)
    counts = {a: sum(p.action == a for _, p in plans) for a in ("start", "resume", "skip", "conflict")}
    print(f"{len(plans)} runs: " + ", ".join(f"{n} {a}" for a, n in counts.items()), file=stream)
    todo = [(spec, plan) for spec, plan in plans if plan.action in ("start", "resume")]
    speeds = measured_speeds(out, [spec for spec, _ in plans])
    probed: set[SpeedKey] = set()
    if probe:
        first_of: dict[SpeedKey, RunSpec] = {}
        for spec, _ in todo:
            first_of.setdefault(speed_key(spec), spec)
        for key, spec in first_of.items():
            if key in speeds:
                continue
            print(f"probing {'/'.join(key)}: {PROBE_WARMUP_STEPS + PROBE_MEASURED_STEPS} steps ...", end=" ",
                  file=stream, flush=True)
            result = probe_speed(spec)
            if result.steps_per_s is None:
                print(f"failed ({result.error})", file=stream, flush=True)
                continue
            speeds[key] = result.steps_per_s
            probed.add(key)
            print(f"{result.steps_per_s:.1f} steps/s", file=stream, flush=True)
    seconds, unknown = 0.0, set()
    for spec, plan in todo:
        status = read_json(spec.run_dir(out) / "status.json") or {} if plan.action == "resume" else {}
        done = int(status.get("step", 0))
        key = speed_key(spec)
        if key in speeds:
            seconds += max(0, spec.steps - done) / speeds[key]
        else:
            unknown.add("/".join(key))
    parallel = max(1, workers or 1)
    source = ("the steps/s of the runs here and of the probes" if probed else "the steps/s the runs here logged")
    if seconds:
        print(f"estimate: {seconds / parallel / 3600:.1f} h with {parallel} worker(s), at {source} "
              "(evaluations excluded)" + (f"; not counted: {', '.join(sorted(unknown))}" if unknown else ""),
              file=stream)
    elif unknown:
        hint = "" if probe else " (--probe times a short run of each)"
        print(f"estimate: none, no run here has logged its speed yet{hint}", file=stream)
    return plans


def run_sweep(grid: SweepGrid, out: str | Path, options: SweepOptions | None = None) -> SweepResult:
    """Run every run of ``grid`` under ``out`` (skipping finished ones) and return what happened."""
    options = options or SweepOptions()
    grid.validate()
    if options.backend not in ("pool", "ray"):
        raise UsageError(f"unknown backend {options.backend!r} (pool or ray)")
    if options.workers is not None and options.workers < 1:
        raise UsageError(f"workers must be >= 1, got {options.workers}")
    out_path = Path(out).resolve()
    out_path.mkdir(parents=True, exist_ok=True)
    result = SweepResult(out_path, len(grid.runs()))
    t0 = time.time()
    with _sweep_lock(out_path), _sigterm_as_interrupt():
        write_manifest(grid, out_path, options)
        todo: list[RunSpec] = []
        for spec in grid.runs():
            plan = plan_run(spec, out_path)
            if plan.action == "skip":
                result.skipped.append(spec.run_id)
                if read_state(spec, out_path).get("state") != "finished":
                    write_state(spec, out_path, state="finished", action="skip", pid=None)
            elif plan.action == "conflict":
                result.failed[spec.run_id] = plan.reason
                write_state(spec, out_path, state="failed", action="conflict", message=plan.reason, pid=None)
            elif busy_elsewhere(spec, out_path):
                result.busy.append(spec.run_id)
            else:
                write_state(spec, out_path, state="pending", pid=None, retries_left=options.retries)
                todo.append(spec)
        stream = options.stream or sys.stdout
        print(f"sweep: {result.total} runs in {out_path} ({len(result.skipped)} already finished, "
              f"{len(todo)} to run on backend {options.backend}); "
              f"TensorBoard for all runs: tensorboard --logdir {out_path}", file=stream, flush=True)
        for run_id in result.busy:
            print(f"sweep: {run_id} is still being trained by an earlier sweep's process; left alone",
                  file=stream, flush=True)
        for run_id, reason in result.failed.items():
            print(f"sweep: CONFLICT {run_id}: {reason}", file=stream, flush=True)
        runner = _run_pool if options.backend == "pool" else _run_ray
        try:
            runner(todo, out_path, options, result, _completed_walls(grid.runs(), out_path))
        except KeyboardInterrupt:
            result.interrupted = True
            print(f"sweep: interrupted; rerun the same command to resume ({out_path})", file=stream,
                  flush=True)
    result.wall_s = time.time() - t0
    return result


def _completed_walls(specs: list[RunSpec], out: Path) -> list[float]:
    """Wall seconds of runs (of this grid) that earlier sweeps finished: a prior for the ETA."""
    walls = []
    for spec in specs:
        state = read_state(spec, out)
        if state.get("state") == "finished" and state.get("wall_s"):
            walls.append(float(state["wall_s"]))
    return walls


def _run_pool(todo: list[RunSpec], out: Path, options: SweepOptions, result: SweepResult,
              prior_walls: list[float]) -> None:
    workers = options.workers or 1
    threads = options.threads or max(1, (os.cpu_count() or 1) // workers)
    progress = Progress(result.total, workers, options)
    progress.walls = list(prior_walls)
    pending: deque[tuple[RunSpec, int]] = deque((spec, options.retries) for spec in todo)
    running: dict[int, tuple[RunSpec, subprocess.Popen[bytes], IO[bytes], float, int]] = {}

    def counts(force: bool = False) -> None:
        now = time.time()
        done = len(result.finished) + len(result.skipped)
        progress.update(done, len(result.skipped), len(result.failed), len(pending),
                        [now - r[3] for r in running.values()], force)

    try:
        counts(force=True)
        while pending or running:
            while pending and len(running) < workers:
                spec, retries_left = pending.popleft()
                plan = plan_run(spec, out)
                if plan.action == "skip":  # finished meanwhile (e.g. by a retry's resume)
                    result.finished.append(spec.run_id)
                    continue
                if plan.action == "conflict":
                    result.failed[spec.run_id] = plan.reason
                    write_state(spec, out, state="failed", action="conflict", message=plan.reason)
                    continue
                attempts = int(read_state(spec, out).get("attempts") or 0) + 1
                proc, cmd, fh = launch(spec, out, plan, threads)
                write_state(spec, out, state="running", action=plan.action, attempts=attempts, pid=proc.pid,
                            host=socket.gethostname(), backend="pool", started=time.time(), command=cmd,
                            retries_left=retries_left, log=str(log_path(spec, out).relative_to(out)))
                running[proc.pid] = (spec, proc, fh, time.time(), retries_left)
                progress.event(f"{plan.action} {spec.run_id} ({plan.reason}) pid {proc.pid}")
                counts()
            for pid in list(running):
                spec, proc, fh, started, retries_left = running[pid]
                rc = proc.poll()
                if rc is None:
                    continue
                fh.close()
                del running[pid]
                wall = time.time() - started
                state = end_state(spec, out, rc, wall)
                if rc == 0:
                    result.finished.append(spec.run_id)
                    progress.walls.append(float(state["wall_s"]))
                    progress.event(f"finished {spec.run_id} in {_hms(wall)}")
                elif rc != USAGE_EXIT and retries_left > 0:
                    pending.append((spec, retries_left - 1))
                    progress.event(f"attempt of {spec.run_id} failed ({state['message']}); will resume it "
                                   f"({retries_left} retr{'y' if retries_left == 1 else 'ies'} left)")
                else:
                    result.failed[spec.run_id] = state["message"]
                    progress.event(f"FAILED {spec.run_id}: {state['message']} (log: {log_path(spec, out)})")
                counts()
            counts()
            time.sleep(0.2)
    except KeyboardInterrupt:
        procs = [r[1] for r in running.values()]
        progress.event(f"stopping {len(procs)} running run(s)...")
        stop_all(procs)
        for spec, proc, fh, started, _ in running.values():
            fh.close()
            rc = proc.returncode if proc.returncode is not None else -9
            end_state(spec, out, rc, time.time() - started)
        raise
    finally:
        progress.close()


def _run_ray(todo: list[RunSpec], out: Path, options: SweepOptions, result: SweepResult,
             prior_walls: list[float]) -> None:
    try:
        import ray
    except ImportError:
        raise UsageError('backend "ray" needs Ray: pip install "mira-rl[ray]" '
                         '(or "ray[default]")') from None
    started_here = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"address": options.address, "include_dashboard": False,
                                  "log_to_driver": False}
        if options.address is None and options.workers is not None:
            kwargs["num_cpus"] = max(1, math.ceil(options.workers * options.cpus_per_run))
        ray.init(**kwargs)
        started_here = True
    try:
        cpus = float(ray.cluster_resources().get("CPU", options.cpus_per_run))
        slots = max(1, int(cpus // options.cpus_per_run))
        threads = options.threads or max(1, int(options.cpus_per_run))
        remote: Any = ray.remote
        task = remote(num_cpus=options.cpus_per_run, max_retries=options.retries,
                      retry_exceptions=[RunFailed])(execute_run)
        progress = Progress(result.total, slots, options)
        progress.walls = list(prior_walls)
        refs: dict[Any, RunSpec] = {}
        for spec in todo:
            write_state(spec, out, state="queued", backend="ray", pid=None)
            refs[task.remote(spec.to_dict(), str(out), threads, "ray")] = spec
        _ray_loop(ray, refs, out, progress, result, options)
    finally:
        if started_here:
            ray.shutdown()


def _ray_loop(ray: Any, refs: dict[Any, RunSpec], out: Path, progress: Progress, result: SweepResult,
              options: SweepOptions) -> None:
    def counts(force: bool = False) -> None:
        now = time.time()
        elapsed, queued = [], 0
        for spec in refs.values():
            state = read_state(spec, out)
            if state.get("state") == "running" and state.get("started"):
                elapsed.append(now - float(state["started"]))
            else:
                queued += 1
        done = len(result.finished) + len(result.skipped)
        progress.update(done, len(result.skipped), len(result.failed), queued, elapsed, force)

    try:
        counts(force=True)
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1, timeout=min(5.0, options.progress_every_s))
            for ref in ready:
                spec = refs.pop(ref)
                try:
                    info = ray.get(ref)
                except Exception as exc:  # RayTaskError wraps RunFailed/RunRejected; also worker crashes
                    reason = _ray_reason(exc)
                    result.failed[spec.run_id] = reason
                    state = read_state(spec, out)
                    if state.get("state") in ("running", "queued"):
                        write_state(spec, out, state="failed", message=reason, pid=None)
                    progress.event(f"FAILED {spec.run_id}: {reason}")
                else:
                    result.finished.append(spec.run_id)
                    wall = float(read_state(spec, out).get("wall_s") or info.get("wall_s") or 0.0)
                    if info.get("action") != "skip":
                        progress.walls.append(wall)
                    progress.event(f"finished {spec.run_id} in {_hms(float(info.get('wall_s', 0.0)))}")
                counts()
            counts()
    except KeyboardInterrupt:
        progress.event(f"cancelling {len(refs)} Ray task(s)...")
        for ref in refs:
            with contextlib.suppress(Exception):
                ray.cancel(ref)
        with contextlib.suppress(Exception):
            ray.wait(list(refs), num_returns=len(refs), timeout=35.0)
        raise
    finally:
        progress.close()


def _ray_reason(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, RunFailed | RunRejected):
        return str(cause)
    lines = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else type(exc).__name__

