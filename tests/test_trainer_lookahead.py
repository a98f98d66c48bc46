"""The trainer's batches sampled ahead (LookaheadSource.lookahead / relabel_many / revision)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from mira.agents.base import AgentConfig
from mira.config import TrainConfig
from mira.loop.hooks import CycleContext
from mira.loop.trainer import Trainer, TrainSetup
from mira.replay import Batch
from mira.rewards.lookahead import LookaheadSource, Relabelled
from mira.runio.rundir import RunDir
from mira.tasks.card import load_task


class AheadReward(LookaheadSource):
    """The episodic reward, relabelled ``ahead`` batches at a time; records what the trainer does."""

    name = "ahead"

    def __init__(self, ahead: int) -> None:
        self.ahead, self._revision = ahead, 0
        self.groups: list[list[int]] = []  # ids of the batches of each relabel_many call
        self.used: list[int] = []  # ids of the batches the agent was updated on, in order
        self.rewards: dict[int, torch.Tensor] = {}
        self.alive: list[Batch] = []  # keeps every batch alive, so ids stay unique

    def relabel(self, batch: Batch) -> torch.Tensor:
        return batch.reward * 1.0

    def lookahead(self) -> int:
        return self.ahead

    def relabel_many(self, batches: list[Batch]) -> list[Relabelled]:
        self.groups.append([id(b) for b in batches])
        self.alive.extend(batches)
        out = super().relabel_many(batches)
        self.rewards.update({id(b): r for b, r in zip(batches, out, strict=True)})
        return out

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        self.used.append(id(batch))
        return {}

    @property
    def revision(self) -> int:
        return self._revision


class BumpRevision:
    """A hook that changes the reward function (as an accepted program edit would)."""

    interval = 17

    def __init__(self, reward: AheadReward) -> None:
        self.reward, self.bumped_at = reward, []

    def on_cycle(self, ctx: CycleContext) -> dict[str, float]:
        self.reward._revision += 1
        self.bumped_at.append(ctx.step)
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        return None


def test_batches_sampled_ahead_are_used_once_in_order_and_dropped_when_stale(tmp_path: Path) -> None:
    reward = AheadReward(ahead=4)
    hook = BumpRevision(reward)
    config = TrainConfig(algo="ddpg", steps=60, seed=0, learning_starts=10, buffer_size=1000, eval_every=10_000,
                         eval_episodes=1, checkpoint_every=30, log_every=1000, max_episode_steps=15,
                         agent=AgentConfig(hidden=(8, 8), batch_size=8))
    setup = TrainSetup(config=config, card=load_task("halfcheetah"), device=torch.device("cpu"), reward=reward,
                       hooks=[hook], quiet=True)
    trainer = Trainer(setup, RunDir(tmp_path))
    seen_rewards: list[torch.Tensor] = []
    update = trainer.agent.update
    trainer.agent.update = lambda batch, r: (seen_rewards.append(r), update(batch, r))[1]  # type: ignore[method-assign]
    trainer.run()

    assert len(reward.used) == 50 and len(set(reward.used)) == 50  # one fresh batch per update
    assert all(len(g) == 4 for g in reward.groups)
    # each update gets the reward relabelled for its own batch, in the order the group was sampled
    assert all(r is reward.rewards[b] for r, b in zip(seen_rewards, reward.used, strict=True))
    position = {b: (g, i) for g, group in enumerate(reward.groups) for i, b in enumerate(group)}
    used_positions = [position[b] for b in reward.used]
    assert used_positions == sorted(used_positions)
    # Updates run from step 11, four per group. A group is cut short only by a change of the reward
    # function (the hook after steps 17, 34, 51) or by a checkpoint (the episode end at step 30):
    # group 1 (steps 15-17), group 5 (step 30) and group 11 (step 51); group 6 (31-34) ends as the
    # revision moves. Everything else is used up before the next group is sampled.
    assert hook.bumped_at == [17, 34, 51]
    used_per_group = [sum(position[b][0] == g for b in reward.used) for g in range(len(reward.groups))]
    assert used_per_group[:-1] == [4, 3, 4, 4, 4, 1, 4, 4, 4, 4, 4, 1, 4, 4]


class ReadStatus:
    """A hook that reads the run's status.json every cycle, as a person watching the run would."""

    interval = 20

    def __init__(self, path: Path) -> None:
        self.path = path
        self.seen: list[dict] = []

    def on_cycle(self, ctx: object) -> dict[str, float]:
        import json

        self.seen.append(json.loads((self.path / "status.json").read_text()))
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        return None


def test_status_json_is_live_while_the_run_goes(tmp_path: Path) -> None:
    from mira.rewards.base import SparseReward

    watcher = ReadStatus(tmp_path)
    config = TrainConfig(algo="ddpg", steps=100, seed=0, learning_starts=10, buffer_size=1000, eval_every=40,
                         eval_episodes=1, checkpoint_every=1000, log_every=20, max_episode_steps=15,
                         agent=AgentConfig(hidden=(8, 8), batch_size=8))
    setup = TrainSetup(config=config, card=load_task("halfcheetah"), device=torch.device("cpu"),
                       reward=SparseReward(), hooks=[watcher], quiet=True)
    Trainer(setup, RunDir(tmp_path)).run()
    steps = [s["step"] for s in watcher.seen]
    assert all(s["status"] == "running" for s in watcher.seen)
    assert steps == sorted(steps) and steps[-1] >= 60 and len(set(steps)) >= 3  # it advances as the run goes
    assert watcher.seen[-1]["steps_per_s"] > 0 and watcher.seen[-1]["last_eval_return"] is not None
