from __future__ import annotations

import numpy as np
import pytest

from mira.tasks import load_task, make_env


def _run_episode(task: str, max_steps: int | None, seed: int) -> tuple[list[float], list[float], bool]:
    env = make_env(load_task(task), max_episode_steps=max_steps)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    rewards, dense = [], []
    while True:
        _, r, term, trunc, info = env.step(rng.uniform(-1, 1, env.action_space.shape))
        rewards.append(float(r))
        dense.append(info["dense_reward"])
        if term or trunc:
            return rewards, dense, term


def test_truncated_episode_delivers_whole_sum_at_last_step() -> None:
    rewards, dense, terminated = _run_episode("halfcheetah", 50, 0)
    assert not terminated and len(rewards) == 50
    assert all(r == 0.0 for r in rewards[:-1])
    assert rewards[-1] == pytest.approx(sum(dense))  # the last step's own reward included
    assert dense[-1] != 0.0


def test_terminated_episode_delivers_whole_sum() -> None:
    rewards, dense, terminated = _run_episode("humanoid", None, 3)  # random actions fall quickly
    assert terminated
    assert all(r == 0.0 for r in rewards[:-1])
    assert rewards[-1] == pytest.approx(sum(dense))


def test_actions_are_rescaled_to_unit_box() -> None:
    env = make_env(load_task("humanoidstandup"))
    assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)
