"""The one training loop, shared by every method.

collect -> store -> sample -> relabel (the method's reward source) -> update agent -> update source
-> evaluate / log / run outer-loop hooks / checkpoint. Methods differ only in the reward source and
the hooks they bring; nothing in this loop knows which method runs.

Checkpoints are taken at episode boundaries (the first one after every ``checkpoint_every`` steps),
so the environment's state is just its random generator: a resumed run continues bit-for-bit on CPU.
"""

from __future__ import annotations

import logging
import math
import random
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
from tqdm import tqdm

from mira.agents import Agent, make_agent
from mira.agents.base import AgentConfig
from mira.errors import CheckpointError, Interrupted, NonFiniteError
from mira.loop.evaluation import EvalResult, collect_rollout, evaluate
from mira.loop.hooks import CycleContext, CycleHook
from mira.loop.metrics import MetricSums
from mira.loop.policies import PolicyKeeper
from mira.loop.rollout import Rollout
from mira.loop.stop import StopRequest
from mira.replay import Batch, ReplayBuffer
from mira.rewards.base import RewardContext, RewardSource
from mira.rewards.lookahead import LookaheadSource, Relabelled, resolve
from mira.runio.checkpoint import load_latest, save_checkpoint
from mira.runio.logger import CsvSink, RunLogger, TensorBoardSink
from mira.runio.rundir import EVAL_FIELDS, RunDir
from mira.tasks.card import TaskCard
from mira.tasks.envs import EpisodicRewardWrapper, make_env, native_action_space

log = logging.getLogger(__name__)

EVAL_SEED_OFFSET = 1_000_003
HOLDOUT_SEED_OFFSET = 2_000_003


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class RunSettings(Protocol):
    """What the trainer reads of a run's configuration (:class:`mira.config.TrainConfig` has it all)."""

    algo: str
    steps: int
    seed: int
    learning_starts: int
    buffer_size: int
    eval_every: int
    eval_episodes: int
    checkpoint_every: int
    log_every: int
    max_episode_steps: int | None
    agent: AgentConfig


@dataclass
class TrainSetup:
    """One run, built: what the trainer reads of the configuration, the task, where to compute, and the
    method's reward source and hooks (:func:`mira.methods.build_method`)."""

    config: RunSettings
    card: TaskCard
    device: torch.device
    reward: RewardSource
    hooks: list[CycleHook] = field(default_factory=list)
    quiet: bool = False
    fork_step: int | None = None
    """For a fork (``mira train --fork``): the parent's step it continues from. Starting from the checkpoint
    of that step, the run draws every random stream afresh from its own seed."""
    fork_program: Any | None = None
    """For a fork with ``--fork-program``: the factor program its hooks install at the fork."""


@dataclass
class TrainResult:
    final_eval: EvalResult | None
    steps: int
    wall_s: float


class Trainer:
    def __init__(self, setup: TrainSetup, run: RunDir) -> None:
        self.setup = setup
        self.run_dir = run
        card = setup.card
        cfg = setup.config
        self.env: EpisodicRewardWrapper = make_env(card, seed=cfg.seed, max_episode_steps=cfg.max_episode_steps)
        self.eval_env = make_env(card, seed=cfg.seed + EVAL_SEED_OFFSET, max_episode_steps=cfg.max_episode_steps)
        obs_dim = int(self.env.observation_space.shape[0])  # type: ignore[index]
        act_dim = int(self.env.action_space.shape[0])  # type: ignore[index]
        self.obs_dim, self.act_dim = obs_dim, act_dim
        _seed_everything(setup.config.seed)
        self.rng = np.random.default_rng(setup.config.seed)
        self.buffer = ReplayBuffer(min(setup.config.buffer_size, max(setup.config.steps, 1)), obs_dim, act_dim)
        self.agent: Agent = make_agent(setup.config.algo, obs_dim, act_dim, setup.config.agent, setup.device)
        self.reward = setup.reward
        self.reward.bind(
            RewardContext(card, obs_dim, act_dim, setup.config.agent.gamma, setup.device, self.buffer,
                          setup.config.seed, run.path)
        )
        self.step = 0
        self.episode = 0
        self.last_eval: EvalResult | None = None
        self.recent_returns: list[float] = []
        self._next_ckpt = setup.config.checkpoint_every
        self._obs: np.ndarray | None = None
        # Batches sampled and relabelled ahead (see LookaheadSource), with the source's revision
        # when they were relabelled: used one per update, dropped when the revision moves or at a checkpoint.
        self._ahead: list[tuple[Batch, Relabelled]] = []
        self._ahead_revision = -1
        self.csv: CsvSink | None = None
        self.logger: RunLogger | None = None
        """The run's logs (CSV files and TensorBoard), opened when training starts."""
        self.policies = PolicyKeeper(run.path, card, cfg, native_action_space(self.env), obs_dim, act_dim,
                                     cfg.seed + EVAL_SEED_OFFSET)

    # ----------------------------------------------------------------------------------------- run
    def run(self) -> TrainResult:
        """Train to the step budget. SIGINT and SIGTERM stop the run after the step in progress, with a
        checkpoint there (:mod:`mira.loop.stop`), raising :class:`~mira.errors.Interrupted`."""
        with StopRequest() as stop:
            return self._run(stop)

    def _run(self, stop: StopRequest) -> TrainResult:
        s = self.setup
        resumed = self._restore()
        # Rows and events logged after the checkpoint will be logged again, identically: the sinks drop them
        # first (TensorBoard from the step after it on: what was logged at the checkpoint's own step stays,
        # as in the CSVs).
        had_events = any((self.run_dir.path / "tb").glob("events.*"))
        self.csv = CsvSink(self.run_dir.path, {"eval": EVAL_FIELDS, "train": self._train_fields()}, self.step)
        self.logger = RunLogger([self.csv, TensorBoardSink(self.run_dir.path / "tb",
                                                           self.step + 1 if resumed or had_events else None,
                                                           skip={"eval": ("episodes", "wall_s")})])
        self.run_dir.set_status("running", self.step)
        if self._obs is None:
            self._obs, _ = self.env.reset(seed=s.config.seed)
        obs = self._obs
        device = s.device
        sums = MetricSums()
        t_start = time.perf_counter()
        t_window, step_window = t_start, self.step
        bar = tqdm(total=s.config.steps, initial=self.step, disable=s.quiet, unit="step", dynamic_ncols=True,
                   smoothing=0.05)
        postfix: dict[str, Any] = {}

        while self.step < s.config.steps:
            if stop.signum is not None:
                self._stop(stop.signum)
            # -- collect and store
            if self.step < s.config.learning_starts:
                action = self.rng.uniform(-1.0, 1.0, self.act_dim).astype(np.float32)
            else:
                action = self.agent.act(obs)
            next_obs, reward, terminated, truncated, info = self.env.step(action)
            row = self.buffer.add(obs, action, float(reward), info["dense_reward"], next_obs, terminated, truncated,
                                  self.episode)
            self.reward.on_transition(row)
            self.step += 1
            obs = next_obs

            # -- sample, relabel, update
            if self.step > s.config.learning_starts and self._can_sample():
                batch, shaped = self._next_batch(device)
                metrics = self.agent.update(batch, shaped)
                metrics.update(self.reward.update(batch, self.step))
                if not sums.add(metrics):
                    self._non_finite(metrics)

            if self.step % s.config.eval_every == 0 or self.step == s.config.steps:
                self.last_eval = evaluate(self.agent, self.eval_env, s.config.eval_episodes,
                                          s.config.seed + EVAL_SEED_OFFSET)
                self.logger.record("eval", self.step, {
                    "return_mean": self.last_eval.mean, "return_std": self.last_eval.std,
                    "length_mean": float(self.last_eval.lengths.mean()), "episodes": s.config.eval_episodes,
                    "wall_s": round(time.perf_counter() - t_start, 3)})
                self.policies.on_evaluation(self.agent, self.step, self.last_eval, self.step == s.config.steps)
                postfix["eval"] = f"{self.last_eval.mean:.1f}"
                if s.quiet:
                    log.info("step %d: eval return %.2f ± %.2f", self.step, self.last_eval.mean, self.last_eval.std)

            for hook in s.hooks:
                if self.step % hook.interval == 0:
                    scalars = hook.on_cycle(self._cycle_context())
                    self.logger.record("outer", self.step, scalars)
                    postfix.update({n: f"{x:.3g}" for n, x in scalars.items() if n in ("trigger", "version")})
                    if "S" in scalars:  # the anomaly score is undefined until the monitor has warmed up
                        postfix["S"] = f"{scalars['S']:.3g}" if math.isfinite(scalars["S"]) else "warming up"

            if self.step % s.config.log_every == 0:
                now = time.perf_counter()
                sps = (self.step - step_window) / max(now - t_window, 1e-9)
                t_window, step_window = now, self.step
                row_out: dict[str, Any] = {"episodes": self.episode, "steps_per_s": round(sps, 2),
                                           "train_return": self.recent_returns[-1] if self.recent_returns else ""}
                row_out.update(sums.means())
                self.csv.widen("train", self._train_fields())  # a new program's factors bring new columns
                self.logger.record("train", self.step, row_out)
                sums.clear()
                self.run_dir.set_status(
                    "running", self.step, steps_per_s=round(sps, 2),
                    last_eval_return=None if self.last_eval is None else round(self.last_eval.mean, 3),
                    program_version=int(float(postfix["version"])) if "version" in postfix else None)
                postfix["sps"] = f"{sps:.0f}"
                bar.set_postfix(postfix, refresh=False)
            bar.update(1)

            # -- episode boundary: report to the source, checkpoint, reset
            if terminated or truncated:
                rows = self.buffer.finish_episode(float(info["episode_return"]))
                self.reward.on_episode_end(rows, float(info["episode_return"]))
                self.recent_returns = [*self.recent_returns, float(info["episode_return"])][-10:]
                self.episode += 1
                if self.step >= self._next_ckpt or self.step >= s.config.steps:
                    self._checkpoint()
                obs, _ = self.env.reset()

        bar.close()
        if not self._checkpointed_at(self.step):
            self._checkpoint(final_partial_episode=True)
        self.reward.close()
        self.run_dir.set_status("finished", self.step)
        self.logger.close()
        return TrainResult(self.last_eval, self.step, time.perf_counter() - t_start)

    # ------------------------------------------------------------------------------------ helpers
    def _non_finite(self, metrics: dict[str, torch.Tensor]) -> None:
        """NaN/Inf in a loss or in Φ: stop with the context, keeping the last checkpoint as the resume point.

        Skipping the update is not an option once an optimiser has stepped on non-finite gradients (the
        parameters are already poisoned), so the policy is to stop the run cleanly: nothing after the
        last checkpoint is kept, and the message names the step and every non-finite quantity.
        """
        bad = MetricSums.non_finite(metrics)
        raise NonFiniteError(
            f"step {self.step}: non-finite {', '.join(bad)} (episode {self.episode}); the run stopped and its last "
            f"checkpoint is intact: lower the learning rate or check the reward program, then --resume"
        )

    def _next_batch(self, device: torch.device) -> tuple[Batch, torch.Tensor]:
        """The next update's batch and its relabelled reward. A source whose reward stays fixed over
        several updates gets their batches sampled now and relabels them together; those batches are
        drawn from the buffer as it is now (the last few stored steps join from the next draw on)."""
        size = self.setup.config.agent.batch_size
        source = self.reward
        if not isinstance(source, LookaheadSource):
            batch = self.buffer.gather(source.sample_rows(size, self.rng)).to(device)
            return batch, source.relabel(batch)
        if not self._ahead or self._ahead_revision != source.revision:
            n = max(1, source.lookahead())
            batches = [self.buffer.gather(source.sample_rows(size, self.rng)).to(device) for _ in range(n)]
            self._ahead = list(zip(batches, source.relabel_many(batches), strict=True))
            self._ahead_revision = source.revision
        batch, reward = self._ahead.pop(0)
        return batch, resolve(reward)

    def _can_sample(self) -> bool:
        if self.reward.needs_complete_episodes:
            return self.buffer.completed_size > 0
        return self.buffer.size > 0

    def _train_fields(self) -> list[str]:
        base = ["step", "episodes", "steps_per_s", "train_return", "critic_loss", "q_mean", "actor_loss",
                "entropy", "alpha"]
        return base + [f for f in getattr(self.reward, "log_fields", ()) if f not in base]

    def _cycle_context(self) -> CycleContext:
        def rollout(episodes: int, seed_base: int) -> Rollout:
            seed = self.setup.config.seed + HOLDOUT_SEED_OFFSET + seed_base
            return collect_rollout(self.agent, self.eval_env, episodes, seed)

        return CycleContext(step=self.step, agent=self.agent, buffer=self.buffer, reward=self.reward, run=self.run_dir,
                            last_eval=self.last_eval, rollout=rollout)

    def _checkpointed_at(self, step: int) -> bool:
        return getattr(self, "_last_ckpt_step", -1) == step

    def _stop(self, signum: int) -> None:
        """Stop on a signal between two steps: end the running episode there (truncated, its return so
        far delivered as any episode's is), checkpoint, write ``policy.pt``, raise ``Interrupted``. A
        resumed run starts a fresh episode; up to there it is the run as it went."""
        if self.buffer.open_episode_len:
            ret = self.env.episode_sum
            rows = self.buffer.truncate_open_episode(ret)
            self.reward.on_episode_end(rows, ret)
            self.recent_returns = [*self.recent_returns, ret][-10:]
            self.episode += 1
        if not self._checkpointed_at(self.step):
            self._checkpoint()
        self.policies.on_interrupt(self.agent, self.step)
        self.reward.close()
        if self.logger is not None:
            self.logger.close()
        raise Interrupted(signum, self.step, checkpointed=True)

    def _checkpoint(self, final_partial_episode: bool = False) -> None:
        state = {
            "step": self.step,
            "episode": self.episode,
            "final_partial_episode": final_partial_episode,
            "agent": self.agent.state_dict(),
            "buffer": self.buffer.state_dict(),
            "reward": self.reward.state_dict(),
            "hooks": [h.state_dict() for h in self.setup.hooks],
            "rng": {
                "numpy": self.rng.bit_generator.state,
                "torch": torch.get_rng_state(),
                "python": random.getstate(),
                "env": self.env.unwrapped.np_random.bit_generator.state,
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            },
            "recent_returns": list(self.recent_returns),
            "last_eval": None if self.last_eval is None else {
                "returns": self.last_eval.returns, "lengths": self.last_eval.lengths},
            "policies": self.policies.state_dict(),
        }
        if self.logger is not None:
            self.logger.flush()  # what was logged up to here survives a kill, as the CSV rows do
        save_checkpoint(self.run_dir.checkpoints, self.step, state)
        # Batches sampled ahead are not part of the state: dropping them here, as a resumed run does,
        # keeps the two identical.
        self._ahead = []
        self._last_ckpt_step = self.step
        while self._next_ckpt <= self.step:
            self._next_ckpt += self.setup.config.checkpoint_every

    def _restore(self) -> bool:
        found = load_latest(self.run_dir.checkpoints)
        if found is None:
            if any(self.run_dir.checkpoints.glob("ckpt-*")):
                raise CheckpointError(f"{self.run_dir.checkpoints}: no checkpoint passes its hash check")
            return False
        step, state = found
        if state.get("final_partial_episode") and step < self.setup.config.steps:
            # A run ended mid-episode (its step budget) and is now extended: restart that episode.
            log.warning("checkpoint %d ended mid-episode; the extended run starts a fresh episode", step)
        self.step = state["step"]
        self.episode = state["episode"]
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.reward.load_state_dict(state["reward"])
        for hook, hook_state in zip(self.setup.hooks, state["hooks"], strict=True):
            hook.load_state_dict(hook_state)
        rng = state["rng"]
        self.rng.bit_generator.state = rng["numpy"]
        torch.set_rng_state(rng["torch"])
        random.setstate(rng["python"])
        if rng.get("cuda") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(rng["cuda"])
        if step == self.setup.fork_step:
            self.rng, env_seed = _fork_streams(self.setup.config.seed, step)
            self._obs, _ = self.env.reset(seed=env_seed)
            for hook in self.setup.hooks:
                hook.on_fork(self.run_dir, self.setup.fork_program)
        else:
            self.env.reset(seed=self.setup.config.seed)
            self.env.unwrapped.np_random.bit_generator.state = rng["env"]
            self._obs, _ = self.env.reset()
        self.recent_returns = list(state["recent_returns"])
        if state["last_eval"] is not None:
            le = state["last_eval"]
            self.last_eval = EvalResult(np.asarray(le["returns"]), np.asarray(le["lengths"]))
        self.policies.load_state_dict(state.get("policies"), step)
        self._last_ckpt_step = step
        self._next_ckpt = self.setup.config.checkpoint_every
        while self._next_ckpt <= self.step:
            self._next_ckpt += self.setup.config.checkpoint_every
        log.info("resumed from checkpoint at step %d", step)
        return True


def _fork_streams(seed: int, step: int) -> tuple[np.random.Generator, int]:
    """A fork's start: every random stream of the loop drawn afresh from its seed and the step (Python's,
    NumPy's and torch's global ones here; the replay sampler and the environment's seed returned), so that
    forks of one checkpoint with different seeds part at once and a fork resumed before its first
    checkpoint repeats itself."""
    streams = np.random.SeedSequence([seed, step])
    python_seed, torch_seed, env_seed = (int(x) for x in streams.generate_state(3))
    random.seed(python_seed)
    np.random.seed(python_seed)
    torch.manual_seed(torch_seed)
    return np.random.default_rng(streams.spawn(1)[0]), env_seed


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)
