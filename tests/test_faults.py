"""Fault injection: SIGKILL at fail points and at random instants, full disks, failing LLM endpoints.

Run alone with ``pytest -m faults``; CI runs it with everything else.
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from chat_server import ChatServer, hang, raw, reply, status
from mira.runio.checkpoint import load_latest
from mira.runio.csvlog import read_csv

pytestmark = [pytest.mark.faults, pytest.mark.slow]

STEPS = "3000"
ARGS = ["train", "--task", "halfcheetah", "--method", "mira-no-mcm", "--steps", STEPS, "--seed", "1",
        "--learning-starts", "300", "--batch-size", "32", "--hidden", "16,16", "--eval-every", "400",
        "--eval-episodes", "1", "--max-episode-steps", "100", "--checkpoint-every", "100", "--log-every", "200",
        "--threads", "1", "--quiet", "--set", "mira.mcm.delta_t=400", "--set", "mira.holdout_episodes=1"]
# `python -m mira.cli`, with two of the outer loop's constants patched so that the runs are short: the no-MCM
# ablation calls SRR every cycle (not every 10th) and the efficacy tests run 100 permutations (not 1000).
MIRA_CLI = ["-c", "; ".join([
    "import os, sys", "import mira.outer.loop, mira.srr.reframe",
    "mira.outer.loop.PERIODIC_CYCLES = 1", "mira.srr.reframe.PERMUTATIONS = 100",
    "os.environ.setdefault('PYTHONUNBUFFERED', '1')", "from mira.cli import main", "sys.exit(main(sys.argv[1:]))"])]


def _run(args: list[str], failpoints: str = "", kill_after: float | None = None,
         cwd: Path | None = None) -> int:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MIRA_FAILPOINTS": failpoints}
    proc = subprocess.Popen([sys.executable, *MIRA_CLI, *args], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, cwd=cwd)
    if kill_after is not None:
        try:
            proc.wait(timeout=kill_after)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=600)
    return proc.returncode


def _outcome(run: Path) -> dict[str, object]:
    evals = [(r["step"], r["return_mean"]) for r in read_csv(run / "eval.csv")]
    diag = [(r["step"], r["raw_pvc"], r["score"], r["version"]) for r in read_csv(run / "diagnostics.csv")]
    programs = {p.name: p.read_text() for p in sorted((run / "programs").glob("v*.json"))}
    decisions = {p.parent.name: json.loads(p.read_text())["accepted"]
                 for p in sorted((run / "interventions").glob("*/decision.json"))}
    return {"eval": evals, "diagnostics": diag, "programs": programs, "decisions": decisions}


# The kill test runs longer, so that its bounded attempts (below) cannot reach the end before 20 kills.
KILL_ARGS = [("6000" if a == STEPS else a) for a in ARGS]


def _timed_reference(out: Path) -> tuple[float, float]:
    """Run the reference to completion; return (start-up seconds, training seconds) as this machine measures them."""
    started = time.monotonic()
    proc = subprocess.run([sys.executable, *MIRA_CLI, *KILL_ARGS, "--out", str(out)], capture_output=True,
                          text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    wall = time.monotonic() - started
    assert proc.returncode == 0, proc.stderr[-2000:]
    match = re.search(r"finished \d+ steps in ([0-9.]+) s", proc.stdout)
    assert match, proc.stdout
    training = float(match.group(1))
    return max(wall - training, 0.5), training


# About 60 process starts (each imports torch and MuJoCo): ~500 s on an idle 2-core machine, twice that
# beside training runs. Its own limit, with margin, instead of the suite's 600 s per test.
@pytest.mark.timeout(2400)
def test_kills_at_fail_points_and_random_instants_lose_nothing(tmp_path: Path) -> None:
    ref = tmp_path / "ref"
    startup, training = _timed_reference(ref)
    expected = _outcome(ref)
    assert expected["eval"] and expected["diagnostics"]

    run = tmp_path / "run"
    points = ["checkpoint.after_payload:2", "checkpoint.before_payload:3", "checkpoint.after_manifest:2",
              "srr.before_call:1", "srr.after_reply:1", "program.saved:1", "program.applied:1",
              "checkpoint.after_payload:1", "srr.after_reply:2", "checkpoint.after_manifest:3",
              "checkpoint.before_payload:2", "srr.before_call:2"]
    rng = random.Random(7)
    # Each attempt arms a fail point and a timer: whichever comes first kills the process. The timer is scaled to
    # this machine's own start-up and training time, and every attempt also carries a backstop (a completed
    # checkpoint: 8 for the SRR and program points, which need a cycle boundary, 2 for the random instants), so
    # that no attempt gets far into the run (at most 5,200 of the 6,000 steps over the 12 named points, 200 per
    # random instant) and the number of kills does not depend on how fast the machine is.
    slice_s = training / 40

    def delay() -> float:
        return startup + rng.uniform(0.1, 1.0) * slice_s

    def bounded(point: str) -> str:
        return point if point.startswith("checkpoint.") else f"{point},checkpoint.after_manifest:8"

    # The named fail points go first, so that every one of them is armed before the run can finish.
    schedule = [(bounded(p), delay()) for p in points] + [("checkpoint.after_manifest:2", delay()) for _ in range(48)]
    kills = 0
    finished = False
    for failpoint, kill_after in schedule:
        started = (run / "config.json").exists()
        args = ["train", "--resume", str(run), "--quiet"] if started else [*KILL_ARGS, "--out", str(run)]
        code = _run(args, failpoint, kill_after)
        if code == 0:
            finished = True
            break
        assert code == -signal.SIGKILL, f"unexpected exit {code}"
        kills += 1
    assert kills >= 20, f"only {kills} kills before the run finished"
    while not finished:  # finish the run
        finished = _run(["train", "--resume", str(run), "--quiet"]) == 0
    assert _outcome(run) == expected


def test_disk_full_stops_cleanly_and_resumes(tmp_path: Path) -> None:
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1500k", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root); the RLIMIT_FSIZE variant still runs")
    try:
        run = mnt / "run"
        args = [*ARGS, "--method", "dense", "--out", str(run), "--hidden", "64,64"]
        proc = subprocess.run([sys.executable, "-m", "mira.cli", *args], capture_output=True, text=True,
                              timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert proc.returncode == 1, proc.stderr[-2000:]
        assert "no space left" in proc.stderr and "--resume" in proc.stderr
        assert "Traceback" not in proc.stderr
        found = load_latest(run / "checkpoints")
        assert found is not None  # the last complete checkpoint is intact
        moved = tmp_path / "run"
        shutil.copytree(run, moved)
    finally:
        subprocess.run(["umount", str(mnt)], check=False)
    assert _run(["train", "--resume", str(moved), "--quiet"]) == 0
    assert read_csv(moved / "eval.csv")[-1]["step"] == STEPS


def test_file_size_limit_is_reported_as_disk_full(tmp_path: Path) -> None:
    run = tmp_path / "run"
    code = (
        "import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN);"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000));"
        "from mira.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    args = [*ARGS, "--method", "dense", "--out", str(run), "--hidden", "64,64"]
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "no space left" in proc.stderr and "Traceback" not in proc.stderr
    assert _run(["train", "--resume", str(run), "--quiet"]) == 0


@pytest.mark.parametrize("behaviours", [
    [status(503)] * 10,                      # endpoint down (5xx until the retries run out)
    [status(429, headers={"Retry-After": "0"})] * 10,  # rate-limited throughout
    [raw(b"this is not JSON at all")] * 10,  # garbage on the wire
    [reply("I think you should gate the velocity.")] * 10,  # prose, no JSON
    [hang(5.0)] * 10,                        # slow: every request times out
])
def test_llm_faults_never_stop_training(tmp_path: Path, behaviours: list[object]) -> None:
    program = Path(__file__).parents[1] / "src" / "mira" / "examples" / "halfcheetah_f0.json"
    with ChatServer() as server:
        server.push(*behaviours)  # type: ignore[arg-type]
        run = tmp_path / "run"
        args = [*ARGS, "--steps", "800", "--out", str(run), "--program", str(program), "--llm", "openai:m",
                "--base-url", server.url, "--set", "llm.max_retries=1", "--set", "llm.timeout_s=1"]
        env_code = _run(args)
    assert env_code == 0
    decisions = [json.loads(p.read_text()) for p in sorted((run / "interventions").glob("*/decision.json"))]
    assert len(decisions) == 2 and all(not d["accepted"] and d["failed"] for d in decisions)
    assert read_csv(run / "eval.csv")[-1]["step"] == "800"
