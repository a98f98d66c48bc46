"""Running a trained policy: ``mira eval`` and :func:`mira.evaluate`.

The episodes are the run's own evaluation's: the deterministic policy on the task's environment as
training built it (actions rescaled to [-1, 1], the run's time limit), episode ``k`` reset with seed
``seed_base + k``, the return summed from the environment's own reward. With the run's seeds (the
default) and as many episodes as its evaluations had, the figure is the run's last evaluation in
``eval.csv`` (for ``policy.pt``) or its best (``policy_best.pt``). Videos are recorded by Gymnasium's
``RecordVideo`` from ``render_mode="rgb_array"`` frames, headless where there is no display
(:mod:`mira.tasks.rendering`); rendering does not change the episodes.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mira.agents.policy_file import Policy
from mira.loop.evaluation import evaluate
from mira.tasks.card import TaskCard, card_from_dict
from mira.tasks.envs import make_env


@dataclass
class PlaybackResult:
    """Returns and lengths of the episodes played, their seeds, and the videos written."""

    returns: np.ndarray
    lengths: np.ndarray
    seeds: list[int]
    videos: list[Path] = field(default_factory=list)

    @property
    def mean(self) -> float:
        return float(self.returns.mean())

    @property
    def std(self) -> float:
        return float(self.returns.std())

    def summary(self) -> str:
        n = len(self.seeds)
        seeds = f"seed {self.seeds[0]}" if n == 1 else f"seeds {self.seeds[0]}..{self.seeds[-1]}"
        return (f"return {self.mean:.2f} ± {self.std:.2f} over {n} episode{'s' if n != 1 else ''} ({seeds}), "
                f"mean length {self.lengths.mean():.0f}")


def policy_card(policy: Policy) -> TaskCard:
    """The task card the policy's run trained on (recorded in the policy file)."""
    card = card_from_dict(json.loads(policy.task["card"]), f"{policy.task.get('name')!r} (from {policy.path})")
    card.source_path = policy.task.get("source")
    return card


def evaluate_policy(policy: Policy, episodes: int | None = None, seed: int | None = None,
                    video_dir: str | os.PathLike[str] | None = None) -> PlaybackResult:
    """Play ``episodes`` deterministic episodes (default: as many as the run's evaluations), episode ``k``
    from seed ``seed + k`` (default: the run's evaluation seeds); ``video_dir``: an MP4 per episode."""
    episodes = int(episodes or policy.run.get("eval_episodes") or 10)
    seed_base = int(policy.run.get("eval_seed_base", 0) if seed is None else seed)
    max_steps = policy.task.get("max_episode_steps")
    prefix = f"{policy.task.get('name', 'policy')}-step{policy.run.get('step', 0)}-seed{seed_base}"
    render_mode = None
    if video_dir is not None:
        from mira.tasks.rendering import ensure_offscreen_gl, ensure_video_writer

        ensure_video_writer()
        ensure_offscreen_gl()
        render_mode = "rgb_array"
    env = make_env(policy_card(policy), max_episode_steps=max_steps, render_mode=render_mode)
    if video_dir is not None:
        import gymnasium as gym

        folder = Path(video_dir)
        # Recording sits under the episodic-reward wrapper: what the episodes return is unchanged.
        env.env = gym.wrappers.RecordVideo(env.env, str(folder), episode_trigger=lambda _: True, name_prefix=prefix,
                                           disable_logger=True)
    try:
        result = evaluate(policy, env, episodes, seed_base)  # the episodes a run's evaluations play
    finally:
        env.close()  # writes the last video
    videos = sorted(Path(video_dir).glob(f"{prefix}-episode-*.mp4")) if video_dir is not None else []
    return PlaybackResult(result.returns, result.lengths, [seed_base + k for k in range(episodes)], videos)
