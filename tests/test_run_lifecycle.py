"""A run's life outside the happy path: killed and resumed (TensorBoard agrees with eval.csv, a stale
"running" status is recognised), stopped by SIGTERM (a resumable checkpoint), an environment given as
``module:Env-v0``, and the sweep's ``--seeds 0`` and instant ``--dry-run``."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mira.cli import main
from mira.errors import TaskCardError
from mira.runio.checkpoint import list_checkpoints, load_latest
from mira.runio.csvlog import read_csv
from mira.runio.rundir import stale_reason
from mira.tasks.card import load_task

BASE = ["train", "--task", "halfcheetah", "--method", "dense", "--seed", "0", "--learning-starts", "200",
        "--batch-size", "32", "--hidden", "16,16", "--eval-every", "400", "--eval-episodes", "1",
        "--max-episode-steps", "200", "--checkpoint-every", "400", "--log-every", "200", "--threads", "1", "--quiet"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _tb_scalars(run: Path, tag: str) -> list[tuple[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)]


def test_tensorboard_matches_eval_csv_after_a_kill_and_resume(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """Killed (SIGKILL) right after its checkpoint at step 800, where it had also evaluated: resumed, its
    TensorBoard evaluations are eval.csv's, none dropped at the resume step and none twice."""
    run = tmp_path / "run"
    killed = subprocess.run([sys.executable, "-m", "mira.cli", *BASE, "--steps", "1200", "--out", str(run)],
                            env={**ENV, "MIRA_FAILPOINTS": "checkpoint.after_manifest:2"}, capture_output=True,
                            timeout=300)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    assert list_checkpoints(run / "checkpoints")[-1] == 800
    status = json.loads((run / "status.json").read_text())
    assert status["status"] == "running" and stale_reason(status) is not None
    assert main(["explain", str(run)]) == 0
    assert "stopped without a word (killed?)" in capsys.readouterr().out

    assert main(["train", "--resume", str(run), "--quiet"]) == 0
    evals = [(int(r["step"]), float(r["return_mean"])) for r in read_csv(run / "eval.csv")]
    assert [s for s, _ in evals] == [400, 800, 1200]
    tb = _tb_scalars(run, "eval/return_mean")
    assert [s for s, _ in tb] == [s for s, _ in evals]
    assert [v for _, v in tb] == pytest.approx([v for _, v in evals], rel=1e-6)  # TensorBoard keeps float32
    assert [s for s, _ in _tb_scalars(run, "train/critic_loss")] == [400, 600, 800, 1000, 1200]
    assert json.loads((run / "status.json").read_text())["status"] == "finished"


def test_sigterm_stops_with_a_resumable_checkpoint(tmp_path: Path) -> None:
    """SIGTERM mid-episode, long before the first scheduled checkpoint: the run truncates its episode,
    checkpoints there, writes policy.pt, records "interrupted" and exits 143; --resume finishes it."""
    run = tmp_path / "run"
    args = [a if a != "400" or i != BASE.index("--checkpoint-every") + 1 else "5000" for i, a in enumerate(BASE)]
    proc = subprocess.Popen([sys.executable, "-m", "mira.cli", *args, "--steps", "3000", "--out", str(run)],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        try:
            step = json.loads((run / "status.json").read_text())["step"]
        except (OSError, ValueError, KeyError):
            step = 0
        if step >= 600:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be stopped"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    status = json.loads((run / "status.json").read_text())
    assert status["status"] == "interrupted" and "SIGTERM" in status["message"]
    found = load_latest(run / "checkpoints")
    assert found is not None
    step, state = found
    assert step == status["step"] and step % 200 != 0  # mid-episode: episodes are 200 steps
    assert state["buffer"]["open_episode_len"] == 0  # the running episode was ended there
    import torch

    meta = torch.load(run / "policy.pt", weights_only=True)["run"]
    assert meta["kind"] == "interrupted" and meta["step"] == step and meta["eval_return_mean"] is None
    assert main(["train", "--resume", str(run), "--quiet"]) == 0
    assert json.loads((run / "status.json").read_text())["status"] == "finished"
    assert [int(r["step"]) for r in read_csv(run / "eval.csv")][-1] == 3000


MODULE = '''
import gymnasium as gym

gym.register("MiraTestCheetah-v0", entry_point="gymnasium.envs.mujoco.half_cheetah_v5:HalfCheetahEnv",
             max_episode_steps=100)
'''

CARD = '''
name = "module_cheetah"
env_id = "{module}:{env}"
description = "HalfCheetah registered by a module of the user's own."

[action]
doc = "torques of the six joints"

[[features]]
name = "forward_velocity"
index = 8
units = "m/s"
doc = "velocity of the torso along x"
better = "higher"
'''


def test_a_module_env_id_card_trains(tmp_path: Path) -> None:
    """``env_id = "module:Env-v0"`` as gymnasium.make takes it: the module (here beside the card, not on
    sys.path) is imported, registers the environment, and the run trains and plays it back."""
    (tmp_path / "mira_lifecycle_envs.py").write_text(MODULE)
    card = tmp_path / "card.toml"
    card.write_text(CARD.format(module="mira_lifecycle_envs", env="MiraTestCheetah-v0"))
    run = tmp_path / "run"
    args = ["train", "--task", str(card), "--method", "dense", "--steps", "600", "--learning-starts", "200",
            "--batch-size", "32", "--hidden", "16,16", "--eval-every", "300", "--eval-episodes", "1",
            "--threads", "1", "--quiet", "--out", str(run)]
    assert main(args) == 0
    evals = read_csv(run / "eval.csv")
    assert [r["step"] for r in evals] == ["300", "600"] and evals[0]["length_mean"] == "100.0"
    from mira.agents.policy_file import load_policy

    policy = load_policy(run)
    assert policy.env_id == "mira_lifecycle_envs:MiraTestCheetah-v0"
    assert policy.make_env().spec.id == "MiraTestCheetah-v0"  # type: ignore[union-attr]

    card.write_text(CARD.format(module="mira_no_such_module_here", env="MiraTestCheetah-v0"))
    with pytest.raises(TaskCardError, match="no module 'mira_no_such_module_here'"):
        load_task(str(card))
    (tmp_path / "mira_lifecycle_silent.py").write_text("x = 1\n")
    card.write_text(CARD.format(module="mira_lifecycle_silent", env="MiraTestNobody-v0"))
    with pytest.raises(TaskCardError, match="did not register it"):
        load_task(str(card))


def test_seeds_zero_is_seed_zero_and_dry_run_is_instant(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    from mira.experiments import sweep
    from mira.experiments.cli import main as experiments_main
    from mira.experiments.estimate import ProbeResult, speed_key
    from mira.experiments.grid import parse_seeds

    assert parse_seeds("0") == [0]
    assert parse_seeds("2") == [0, 1]

    def no_probe(*_: object, **__: object) -> None:
        raise AssertionError("--dry-run probed without --probe")

    monkeypatch.setattr(sweep, "probe_speed", no_probe)
    out = tmp_path / "sweep"
    started = time.monotonic()
    assert experiments_main(["sweep", "--tasks", "halfcheetah", "--methods", "dense", "--algos", "sac", "--seeds",
                             "0", "--steps", "1000", "--out", str(out), "--dry-run"]) == 0
    assert time.monotonic() - started < 10
    text = capsys.readouterr().out
    assert "seed0" in text and "seed1" not in text and "1 runs" in text and "--probe" in text
    buf = io.StringIO()
    monkeypatch.setattr(sweep, "probe_speed", lambda spec: ProbeResult(speed_key(spec), 100.0))
    grid_args = ["sweep", "--tasks", "halfcheetah", "--methods", "dense", "--algos", "sac", "--seeds", "0",
                 "--steps", "1000", "--out", str(out), "--dry-run", "--probe"]
    monkeypatch.setattr(sys, "stdout", buf)
    assert experiments_main(grid_args) == 0
    assert "probing" in buf.getvalue()


def test_sweeps_tell_a_vanished_run_from_a_running_one(tmp_path: Path) -> None:
    """status.json says "running": a sweep resumes the run when its process is gone, and leaves it alone
    while a process of this host still trains it."""
    import socket

    from mira.experiments.grid import RunSpec
    from mira.experiments.runs import busy_elsewhere, plan_run
    from mira.runio.rundir import process_identity

    spec = RunSpec("halfcheetah", "dense", "sac", 0, 1000)
    run = spec.run_dir(tmp_path)
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "ckpt-0000000400.json").write_text("{}")
    (run / "config.json").write_text(json.dumps({"config": {"task": "halfcheetah", "method": "dense", "algo": "sac",
                                                            "seed": 0, "steps": 1000}}))
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    (run / "status.json").write_text(json.dumps({"status": "running", "step": 400, "pid": gone.pid,
                                                 "host": socket.gethostname(), "heartbeat": time.time()}))
    plan = plan_run(spec, tmp_path)
    assert plan.action == "resume" and "stopped without a word (killed?)" in plan.reason
    assert not busy_elsewhere(spec, tmp_path)
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        ident = process_identity()
        (run / "status.json").write_text(json.dumps({"status": "running", "step": 400, "pid": alive.pid,
                                                     "host": ident["host"], "heartbeat": time.time()}))
        assert busy_elsewhere(spec, tmp_path)
        assert "running at step 400" in plan_run(spec, tmp_path).reason
    finally:
        alive.kill()
        alive.wait()
