"""Environment construction and the episodic-reward setting of RRD / IRCR / LaRe.

``EpisodicRewardWrapper`` hides the environment's per-step reward from the agent: every step gives 0
and the episode's last step (termination *or* truncation) gives the sum of all the episode's dense
rewards, the last step's own reward included. The dense reward of each step stays in
``info["dense_reward"]`` for the oracle and for diagnostics; sparse methods never read it.
"""

from __future__ import annotations

import sys
from functools import cache
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from mira.errors import TaskCardError
from mira.tasks.card import TaskCard, import_env_module


class EpisodicRewardWrapper(gym.Wrapper[np.ndarray, np.ndarray, np.ndarray, np.ndarray]):
    """Deliver the whole episode's return at its last step and 0 elsewhere."""

    def __init__(self, env: gym.Env[np.ndarray, np.ndarray]) -> None:
        super().__init__(env)
        self._episode_sum = 0.0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        self._episode_sum = 0.0
        return self.env.reset(seed=seed, options=options)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        dense = float(reward)
        self._episode_sum += dense
        info["dense_reward"] = dense
        if terminated or truncated:
            episodic = self._episode_sum
            info["episode_return"] = episodic
            self._episode_sum = 0.0
            return obs, episodic, terminated, truncated, info
        return obs, 0.0, terminated, truncated, info

    @property
    def episode_sum(self) -> float:
        """Dense return accumulated so far in the running episode (checkpointed with the run)."""
        return self._episode_sum

    @episode_sum.setter
    def episode_sum(self, value: float) -> None:
        self._episode_sum = float(value)


QUIET_MUJOCO_WARNINGS = ("compiler attribute 'settotalmass' is deprecated",)
"""MuJoCo warnings that say nothing about the user's run: Gymnasium's own model files still use an
attribute MuJoCo 3.3 deprecated, and every environment built would print it."""


@cache
def _filter_mujoco_warnings() -> None:
    """Drop exactly the :data:`QUIET_MUJOCO_WARNINGS` (by message prefix); print every other MuJoCo
    warning as MuJoCo itself does. Installed once, before the first environment is built."""
    try:
        import mujoco
    except ImportError:  # a task without MuJoCo: nothing to filter
        return
    previous = mujoco.get_mju_user_warning()

    def on_warning(message: str) -> None:
        if message.startswith(QUIET_MUJOCO_WARNINGS):
            return
        if previous is not None:
            previous(message)
        else:
            print(f"WARNING: {message}\n", file=sys.stderr)

    mujoco.set_mju_user_warning(on_warning)


def action_dim(card: TaskCard) -> int:
    """Size of the task's action vector (builds the environment once to read it)."""
    env = make_env(card)
    try:
        return int(env.action_space.shape[0])  # type: ignore[index]
    finally:
        env.close()


def make_env(card: TaskCard, seed: int | None = None, max_episode_steps: int | None = None,
             render_mode: str | None = None) -> EpisodicRewardWrapper:
    """Create the task's environment with actions rescaled to [-1, 1] and the episodic reward.

    The card is bound to the observation size, so a feature index outside the observation is
    reported here, before any training. An ``env_id`` written ``module:Env-v0`` imports ``module``
    first (:func:`~mira.tasks.card.import_env_module`). ``render_mode`` goes to ``gymnasium.make``
    (``"rgb_array"`` for videos).
    """
    _filter_mujoco_warnings()
    env_id = import_env_module(card.env_id, card.source_path)
    try:
        kwargs = dict(card.env_kwargs)
        if max_episode_steps is not None:
            kwargs["max_episode_steps"] = max_episode_steps
        if render_mode is not None:
            kwargs["render_mode"] = render_mode
        env = gym.make(env_id, **kwargs)
    except gym.error.Error as exc:
        raise TaskCardError(f"task {card.name!r}: cannot create environment {card.env_id!r}: {exc}") from exc
    obs_space, act_space = env.observation_space, env.action_space
    if not isinstance(obs_space, gym.spaces.Box) or len(obs_space.shape) != 1:
        raise TaskCardError(f"task {card.name!r}: MIRA needs a flat Box observation space, got {obs_space}")
    if not isinstance(act_space, gym.spaces.Box) or len(act_space.shape) != 1:
        raise TaskCardError(f"task {card.name!r}: MIRA needs a continuous (Box) action space, got {act_space}")
    card.bind(int(obs_space.shape[0]))
    if card.action_names and len(card.action_names) != int(act_space.shape[0]):
        raise TaskCardError(f"task card {card.where}, action: key 'names' lists {len(card.action_names)} names but "
                            f"{card.env_id} has {int(act_space.shape[0])} action dimensions")
    if not (np.all(act_space.low == -1.0) and np.all(act_space.high == 1.0)):
        ones = np.ones(act_space.shape, dtype=np.float32)
        env = gym.wrappers.RescaleAction(env, min_action=-ones, max_action=ones)
    wrapped = EpisodicRewardWrapper(env)
    if seed is not None:
        wrapped.action_space.seed(seed)
    return wrapped


def native_action_space(env: gym.Env[Any, Any]) -> gym.spaces.Box:
    """The environment's own action space under :func:`make_env`'s rescaling to [-1, 1] (what a policy
    file records, so that it can answer in the environment's own bounds)."""
    inner: Any = env
    while isinstance(inner, gym.Wrapper):
        if isinstance(inner, gym.wrappers.RescaleAction):
            inner = inner.env
            break
        inner = inner.env
    space = inner.action_space if isinstance(inner, gym.Env) else env.action_space
    assert isinstance(space, gym.spaces.Box)
    return space
