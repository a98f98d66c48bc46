"""End-to-end runs of ``mira train`` at a few thousand steps (small networks)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mira.cli import main
from mira.runio.checkpoint import list_checkpoints
from mira.runio.csvlog import read_csv

EXPECTED_FILES = ("config.json", "status.json", "eval.csv", "train.csv")


def _train(out: Path, fast: list[str], *extra: str, steps: int = 3000) -> int:
    return main(["train", "--steps", str(steps), "--seed", "0", "--out", str(out), *fast, *extra])


def _eval_rows(run: Path) -> list[tuple[str, ...]]:
    # wall_s is a timing column: everything else must match exactly.
    return [(r["step"], r["return_mean"], r["return_std"], r["length_mean"]) for r in read_csv(run / "eval.csv")]


def _check_run_dir(run: Path, steps: int) -> None:
    for name in EXPECTED_FILES:
        assert (run / name).is_file(), name
    assert any((run / "tb").iterdir())
    assert list_checkpoints(run / "checkpoints")
    rows = read_csv(run / "eval.csv")
    assert int(rows[-1]["step"]) == steps
    train_rows = read_csv(run / "train.csv")
    assert train_rows and "critic_loss" in train_rows[0]
    assert '"finished"' in (run / "status.json").read_text()


@pytest.mark.slow
@pytest.mark.parametrize(
    ("task", "method", "algo"),
    [
        ("halfcheetah", "dense", "sac"),
        ("halfcheetah", "dense", "ddpg"),
        ("halfcheetah", "sparse", "sac"),
        ("humanoidstandup", "dense", "sac"),
        ("humanoid", "sparse", "ddpg"),
    ],
)
def test_train_writes_every_file(tmp_path: Path, fast_train_args: list[str], task: str, method: str, algo: str) -> None:
    run = tmp_path / "run"
    assert _train(run, fast_train_args, "--task", task, "--method", method, "--algo", algo) == 0
    _check_run_dir(run, 3000)


@pytest.mark.slow
def test_same_seed_gives_identical_eval_csv(tmp_path: Path, fast_train_args: list[str]) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    assert _train(a, fast_train_args, steps=1500) == 0
    assert _train(b, fast_train_args, steps=1500) == 0
    assert _eval_rows(a) == _eval_rows(b)
    assert len(_eval_rows(a)) == 2


@pytest.mark.slow
@pytest.mark.parametrize("method", ["dense", "hars"])
def test_sigkill_then_resume_matches_uninterrupted_run(tmp_path: Path, fast_train_args: list[str], method: str) -> None:
    """``hars`` adds learned state beyond the agent's: its networks and optimiser, the factor columns
    (evaluated lazily), the statistics snapshot Φ reads and σ_R."""
    steps = "2400"
    # Every part runs in a fresh process, as a user runs it (the killed run has to anyway).
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ref = tmp_path / "ref"
    base = [sys.executable, "-m", "mira.cli", "train", "--steps", steps, "--seed", "0", "--method", method,
            *fast_train_args]
    assert subprocess.run([*base, "--out", str(ref)], env=env, capture_output=True).returncode == 0

    killed = tmp_path / "killed"
    proc = subprocess.Popen([*base, "--out", str(killed)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if [s for s in list_checkpoints(killed / "checkpoints") if s >= 800]:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert '"running"' in (killed / "status.json").read_text()

    resume = [sys.executable, "-m", "mira.cli", "train", "--resume", str(killed), "--quiet"]
    assert subprocess.run(resume, env=env, capture_output=True).returncode == 0
    assert _eval_rows(killed) == _eval_rows(ref)


@pytest.mark.slow
def test_resume_with_larger_steps_extends_the_run_as_if_started_with_them(
        tmp_path: Path, fast_train_args: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """A finished 1,200-step run extended with ``--resume DIR --steps 2400`` logs what a 2,400-step run
    logs (its replay buffer grows on restore); only the extra evaluation at its old budget differs."""
    ref, short = tmp_path / "ref", tmp_path / "short"
    # train.csv averages over each log interval: the old budget is made an interval's end.
    args = [*fast_train_args, "--log-every", "400", "--method", "hars"]
    assert _train(ref, args, steps=2400) == 0
    assert _train(short, args, steps=1200) == 0
    assert main(["train", "--resume", str(short), "--steps", "600", "--quiet"]) == 2
    assert "can only extend" in capsys.readouterr().err
    assert main(["train", "--resume", str(short), "--steps", "2400", "--quiet"]) == 0
    assert [r for r in _eval_rows(short) if r[0] != "1200"] == _eval_rows(ref)
    drop = ("steps_per_s",)
    assert ([{k: v for k, v in r.items() if k not in drop} for r in read_csv(short / "train.csv")]
            == [{k: v for k, v in r.items() if k not in drop} for r in read_csv(ref / "train.csv")])
    saved = json.loads((short / "config.json").read_text())
    assert saved["config"]["steps"] == 2400 and saved["extended_from"] == [1200]
