"""Using a trained policy: policy files, ``load_policy`` / ``predict``, ``mira eval`` (with videos,
headless), the Python API and the README's example of it."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import mira
from mira.agents.networks import DeterministicActor
from mira.agents.policy_file import PolicyFileError, load_policy, policy_payload, save_policy
from mira.cli import main
from mira.errors import UsageError
from mira.runio.csvlog import read_csv

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--learning-starts", "300", "--batch-size", "64", "--hidden", "32,32", "--eval-every", "500",
        "--eval-episodes", "1", "--max-episode-steps", "100", "--checkpoint-every", "500", "--log-every", "500",
        "--threads", "1", "--quiet"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2,000-step dense SAC run on HalfCheetah (evaluations every 500 steps, one 100-step episode each)."""
    run = tmp_path_factory.mktemp("policy") / "run"
    assert main(["train", "--task", "halfcheetah", "--method", "dense", "--steps", "2000", "--seed", "0",
                 "--out", str(run), *FAST]) == 0
    return run


def _episode(policy: mira.Policy, seed: int) -> float:
    env = policy.make_env()
    obs, _ = env.reset(seed=seed)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(policy.predict(obs))
        total += float(reward)
        done = terminated or truncated
    env.close()
    return total


def test_policy_files_are_small_plain_data(trained: Path) -> None:
    for name in ("policy.pt", "policy_best.pt"):
        path = trained / name
        assert path.stat().st_size < 200_000  # the checkpoints hold the replay buffer; this does not
        data = torch.load(path, weights_only=True)
        assert data["format"] == "mira-policy" and data["algo"] == "sac" and data["hidden"] == [32, 32]
        assert data["obs_dim"] == 17 and data["act_dim"] == 6 and data["task"]["env_id"] == "HalfCheetah-v5"
        assert not any(k in data for k in ("critic", "buffer", "actor_opt"))
    evals = read_csv(trained / "eval.csv")
    final, best = load_policy(trained), load_policy(trained, best=True)
    assert final.run["kind"] == "final" and final.run["step"] == 2000
    best_row = max(evals, key=lambda r: float(r["return_mean"]))
    assert best.run["kind"] == "best" and best.run["step"] == int(best_row["step"])
    assert best.run["eval_return_mean"] == float(best_row["return_mean"])


def test_predict_repeats_the_runs_evaluation(trained: Path) -> None:
    """One deterministic episode from the run's evaluation seed, on a plain Gymnasium environment,
    returns exactly what eval.csv recorded for those weights."""
    evals = read_csv(trained / "eval.csv")
    for best in (False, True):
        policy = mira.load_policy(trained, best=best)
        row = next(r for r in evals if int(r["step"]) == policy.run["step"])
        assert _episode(policy, policy.run["eval_seed_base"]) == float(row["return_mean"])
    # A batch answers as the observations one by one do (up to the rounding of matrix products).
    obs = np.random.default_rng(0).normal(size=(5, 17))
    batch = policy.predict(obs)
    assert batch.shape == (5, 6) and np.all(np.abs(batch) <= 1)
    np.testing.assert_allclose(batch, np.stack([policy.predict(o) for o in obs]), atol=1e-5)


def test_mira_eval_prints_the_runs_figure(trained: Path, capsys: pytest.CaptureFixture[str]) -> None:
    last = read_csv(trained / "eval.csv")[-1]
    assert main(["eval", str(trained)]) == 0
    out = capsys.readouterr().out
    assert f"return {float(last['return_mean']):.2f} ± 0.00 over 1 episode (seed 1000003)" in out
    assert main(["eval", str(trained / "policy_best.pt"), "--episodes", "2", "--seed", "7"]) == 0
    assert "over 2 episodes (seeds 7..8)" in capsys.readouterr().out
    assert main(["eval", str(trained / "checkpoints")]) == 2
    assert "no policy.pt" in capsys.readouterr().err
    ckpt = next((trained / "checkpoints").glob("ckpt-*.pt"))
    assert main(["eval", str(ckpt)]) == 2
    err = capsys.readouterr().err
    assert "not a MIRA policy file" in err or "not a readable policy file" in err


def test_mira_eval_video_headless(trained: Path, tmp_path: Path) -> None:
    """No display and no MUJOCO_GL: the command picks a headless backend and writes a playable MP4."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MUJOCO_GL",
                                                            "PYOPENGL_PLATFORM")}
    videos = tmp_path / "videos"
    done = subprocess.run([sys.executable, "-m", "mira.cli", "eval", str(trained), "--video", str(videos)],
                          env={**env, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    files = sorted(videos.glob("*.mp4"))
    assert len(files) == 1 and files[0].stat().st_size > 1000
    assert f"video {files[0]}" in done.stdout
    import imageio_ffmpeg

    frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(files[0]))
    assert frames >= 100 and seconds > 0  # one frame per step of the 100-step episode, and the first


def test_actions_land_in_the_environments_bounds() -> None:
    """Humanoid's actions are in [-0.4, 0.4]: ``predict`` maps the actor's [-1, 1] as RescaleAction does
    in training; ``act`` is the actor's own action."""
    env = gym.make("Humanoid-v5")
    space = env.action_space
    assert isinstance(space, gym.spaces.Box)
    obs_dim, act_dim = int(env.observation_space.shape[0]), int(space.shape[0])  # type: ignore[index]
    actor = DeterministicActor(obs_dim, act_dim, (8,))
    payload = policy_payload(algo="ddpg", obs_dim=obs_dim, act_dim=act_dim, hidden=(8,),
                             actor_state=actor.state_dict(), action_space=space, exploration_noise=0.1,
                             task={"name": "humanoid", "env_id": "Humanoid-v5", "env_kwargs": "{}",
                                   "max_episode_steps": None, "card": "{}", "source": None},
                             run={"kind": "latest", "step": 0})
    policy = mira.Policy(payload)
    rescaled = gym.wrappers.RescaleAction(env, min_action=-np.ones(act_dim, np.float32),
                                          max_action=np.ones(act_dim, np.float32))
    obs, _ = env.reset(seed=0)
    raw = policy.act(obs)
    assert np.array_equal(policy.predict(obs), rescaled.action(raw))
    noisy = policy.predict(np.stack([obs, obs]), deterministic=False)
    assert noisy.shape == (2, act_dim) and np.all(np.abs(noisy) <= 0.4 + 1e-6)
    env.close()


def test_a_policy_file_round_trips_and_bad_files_are_refused(trained: Path, tmp_path: Path) -> None:
    policy = load_policy(trained)
    copy = save_policy(tmp_path / "p.pt", policy.payload)
    again = load_policy(copy)
    obs = np.zeros(17)
    assert np.array_equal(again.predict(obs), policy.predict(obs))
    (tmp_path / "junk.pt").write_bytes(b"not a policy")
    for bad in (tmp_path / "junk.pt", tmp_path / "missing.pt"):
        with pytest.raises(PolicyFileError):
            load_policy(bad)
    with pytest.raises(PolicyFileError, match="best"):
        load_policy(copy, best=True)


def test_import_mira_is_light_and_exports_the_api() -> None:
    code = ("import sys, mira; assert 'torch' not in sys.modules, 'torch imported'; "
            "assert callable(mira.train) and callable(mira.load_policy) and callable(mira.evaluate); "
            "print(mira.__version__)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    with pytest.raises(AttributeError):
        mira.no_such_name  # noqa: B018


def test_train_api_checks_its_arguments(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no option 'stepz'"):
        mira.train(task="hopper", out=tmp_path / "r", stepz=10)
    with pytest.raises(UsageError, match="algo"):
        mira.train(task="hopper", algo="ppo", out=tmp_path / "r")
    assert not (tmp_path / "r").exists()


def test_readme_python_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    """The README's "Python API" example, at 1,500 steps instead of 30,000, in a scratch directory."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("### Python API", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S)
    assert code is not None
    source = code.group(1)
    assert "steps=30_000" in source
    monkeypatch.chdir(tmp_path)
    exec(compile(source.replace("steps=30_000", "steps=1_500"), "README.md", "exec"), {})
    out = capsys.readouterr().out
    assert "\nfinished " in out and "one episode: " in out and "over 5 episodes" in out
    assert (tmp_path / "runs" / "hopper-api" / "policy.pt").is_file()
