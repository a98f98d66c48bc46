"""Tasks: task cards with named state features, and the episodic-reward environment."""

from mira.tasks.card import Feature, StateView, TaskCard, builtin_task_names, load_task
from mira.tasks.envs import EpisodicRewardWrapper, make_env

__all__ = [
    "EpisodicRewardWrapper",
    "Feature",
    "StateView",
    "TaskCard",
    "builtin_task_names",
    "load_task",
    "make_env",
]
