"""End-to-end sweeps at a tiny budget: local pool with a worker killed mid-run and a rerun, and Ray.

One module-scoped sweep (2 methods × 2 seeds × halfcheetah, 600 steps) is shared: the pool test
kills one run's subprocess with SIGKILL, reruns the sweep, and checks that finished runs are not
touched and the killed one is resumed; the Ray test runs the same grid on a local Ray instance and
compares its report with the pool's, timing columns aside.
"""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from mira.experiments.grid import SweepGrid
from mira.experiments.report import write_report
from mira.experiments.runs import read_state
from mira.experiments.sweep import SweepOptions, run_sweep
from mira.runio.checkpoint import list_checkpoints
from mira.runio.csvlog import read_csv

TINY = ["--learning-starts", "200", "--batch-size", "32", "--hidden", "16,16", "--eval-every", "300",
        "--eval-episodes", "1", "--max-episode-steps", "100", "--checkpoint-every", "200", "--threads", "1"]
GRID = SweepGrid(["halfcheetah"], ["dense", "sparse"], ["sac"], [0, 1], 600, list(TINY))
TIMING = {"wall_s", "wall_s_mean"}


def _mtimes(run: Path) -> dict[str, int]:
    return {str(p.relative_to(run)): p.stat().st_mtime_ns for p in sorted(run.rglob("*")) if p.is_file()}


def _kill_one_mid_run(out: Path, proc: subprocess.Popen[bytes], deadline_s: float = 150.0) -> str | None:
    """SIGKILL the first run subprocess seen with a checkpoint but not yet finished."""
    deadline = time.time() + deadline_s
    while time.time() < deadline and proc.poll() is None:
        for spec in GRID.runs():
            state = read_state(spec, out)
            run = spec.run_dir(out)
            pid = state.get("pid")
            if state.get("state") != "running" or not isinstance(pid, int):
                continue
            status = run / "status.json"
            if list_checkpoints(run / "checkpoints") and '"finished"' not in (
                    status.read_text() if status.exists() else ""):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    continue
                return spec.run_id
        time.sleep(0.05)
    return None


@pytest.fixture(scope="module")
def pool_sweep(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("pool") / "sweep"
    cmd = [sys.executable, "-m", "mira.experiments.cli", "sweep", "--tasks", "halfcheetah",
           "--methods", "dense,sparse", "--algos", "sac", "--seeds", "2", "--steps", "600", "--out", str(out),
           "--workers", "2", "--retries", "0", "--progress-every", "5", "--train-args", " ".join(TINY)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    killed = _kill_one_mid_run(out, proc)
    first_output = proc.communicate(timeout=300)[0].decode()
    info: dict[str, Any] = {"out": out, "killed": killed, "first_rc": proc.returncode, "first_output": first_output}
    if killed is None:
        return info
    specs = {s.run_id: s for s in GRID.runs()}
    info["killed_state"] = read_state(specs[killed], out)
    info["before"] = {rid: _mtimes(s.run_dir(out)) for rid, s in specs.items()}
    buf = io.StringIO()
    info["second"] = run_sweep(GRID, out, SweepOptions(workers=2, retries=0, stream=buf, tqdm=False))
    info["second_output"] = buf.getvalue()
    info["after"] = {rid: _mtimes(s.run_dir(out)) for rid, s in specs.items()}
    info["third"] = run_sweep(GRID, out, SweepOptions(workers=2, stream=io.StringIO(), tqdm=False))
    info["after_third"] = {rid: _mtimes(s.run_dir(out)) for rid, s in specs.items()}
    info["report"] = write_report([out], out.parent / "report", bootstrap_reps=1000)
    return info


@pytest.mark.slow
def test_pool_sweep_survives_a_killed_worker(pool_sweep: dict[str, Any]) -> None:
    out: Path = pool_sweep["out"]
    killed = pool_sweep["killed"]
    assert killed is not None, "no run was caught mid-run:\n" + pool_sweep["first_output"]
    # The first sweep carried on with the others and reported the killed run as failed.
    assert pool_sweep["first_rc"] == 1, pool_sweep["first_output"]
    assert pool_sweep["killed_state"]["state"] == "failed"
    assert "killed by signal 9" in pool_sweep["killed_state"]["message"]
    assert "ETA" in pool_sweep["first_output"] and "tensorboard --logdir" in pool_sweep["first_output"]
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["grid"]["steps"] == 600 and len(manifest["runs"]) == 4

    second = pool_sweep["second"]
    others = sorted(s.run_id for s in GRID.runs() if s.run_id != killed)
    assert second.ok and second.finished == [killed] and sorted(second.skipped) == others
    for rid in others:  # finished runs were skipped: not one file touched
        assert pool_sweep["after"][rid] == pool_sweep["before"][rid], rid
    # The killed run was resumed from its checkpoint, not started over.
    before, after = pool_sweep["before"][killed], pool_sweep["after"][killed]
    assert after["config.json"] == before["config.json"]
    assert f"resume {killed}" in pool_sweep["second_output"]
    spec = next(s for s in GRID.runs() if s.run_id == killed)
    assert [r["step"] for r in read_csv(spec.run_dir(out) / "eval.csv")] == ["300", "600"]
    assert read_state(spec, out)["attempts"] == 2
    # A third sweep has nothing to do.
    third = pool_sweep["third"]
    assert third.ok and not third.finished and len(third.skipped) == 4
    assert pool_sweep["after_third"] == pool_sweep["after"]

    # Every run is in the report, every cell filled.
    report = pool_sweep["report"]
    assert sum(len(c.seeds) for c in report.cells) == 4
    table = (out.parent / "report" / "table_sac.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| ") and "Method" not in line]
    assert len(rows) == 2 and all(cell.strip() for row in rows for cell in row.strip("|").split("|"))
    assert (out.parent / "report" / "curves_sac.png").stat().st_size > 10_000


def _without_timing(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k not in TIMING} for row in csv.DictReader(fh)]


@pytest.mark.slow
def test_ray_sweep_matches_pool(pool_sweep: dict[str, Any], tmp_path: Path) -> None:
    ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'mira-rl[ray]'")
    assert pool_sweep["killed"] is not None
    out = tmp_path / "ray"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        buf = io.StringIO()
        result = run_sweep(GRID, out, SweepOptions(backend="ray", cpus_per_run=1, stream=buf, tqdm=False))
    finally:
        ray.shutdown()
    assert result.ok and len(result.finished) == 4, buf.getvalue()
    for spec in GRID.runs():
        state = read_state(spec, out)
        assert state["state"] == "finished" and state["backend"] == "ray"
    write_report([out], tmp_path / "report", bootstrap_reps=1000)
    pool_report = pool_sweep["out"].parent / "report"
    for name in ("metrics.csv", "table_sac.csv", "runs.csv", "aggregate.csv"):
        assert _without_timing(tmp_path / "report" / name) == _without_timing(pool_report / name), name
    assert (tmp_path / "report" / "table_sac.md").read_text() == (pool_report / "table_sac.md").read_text()
