"""The policy files of a run: ``policy.pt`` at every evaluation (and when the run stops on a signal),
``policy_best.pt`` whenever an evaluation beats every earlier one (format: :mod:`mira.agents.policy_file`).

The best policy so far is part of the run's state: a checkpoint carries it, and a resumed run rewrites
``policy_best.pt`` from it, so that a file written after the checkpoint by the run that was killed
never outlives the history the resumed run replaces it with.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import gymnasium as gym

from mira.agents import Agent
from mira.agents.policy_file import BEST_POLICY_FILE, POLICY_FILE, policy_payload, save_policy
from mira.loop.evaluation import EvalResult
from mira.tasks.card import TaskCard, card_to_dict

log = logging.getLogger(__name__)


class PolicyKeeper:
    """Writes a run's policy files; ``state_dict`` is the best policy so far, for checkpoints."""

    def __init__(self, run_path: Path, card: TaskCard, config: Any, action_space: gym.spaces.Box,
                 obs_dim: int, act_dim: int, eval_seed_base: int) -> None:
        self.path = run_path
        self.config = config
        self.action_space = action_space
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.eval_seed_base = eval_seed_base
        self.task = {"name": card.name, "env_id": card.env_id, "env_kwargs": json.dumps(card.env_kwargs),
                     "max_episode_steps": config.max_episode_steps, "card": json.dumps(card_to_dict(card)),
                     "source": card.source_path, "spec": str(getattr(config, "task", card.name))}
        self.best_return: float | None = None
        self.best: dict[str, Any] | None = None

    def _payload(self, agent: Agent, kind: str, step: int, result: EvalResult | None) -> dict[str, Any]:
        cfg = self.config
        run = {"kind": kind, "step": int(step), "seed": int(cfg.seed), "method": str(getattr(cfg, "method", "")),
               "eval_seed_base": int(self.eval_seed_base), "eval_episodes": int(cfg.eval_episodes),
               "eval_return_mean": None if result is None else float(result.mean),
               "eval_return_std": None if result is None else float(result.std)}
        return policy_payload(algo=cfg.algo, obs_dim=self.obs_dim, act_dim=self.act_dim, hidden=cfg.agent.hidden,
                              actor_state=agent.actor_state(), action_space=self.action_space,
                              exploration_noise=cfg.agent.exploration_noise, task=self.task, run=run)

    def on_evaluation(self, agent: Agent, step: int, result: EvalResult, final: bool) -> None:
        """``policy.pt`` with these weights and their evaluation; ``policy_best.pt`` too if it is the best."""
        payload = self._payload(agent, "final" if final else "latest", step, result)
        save_policy(self.path / POLICY_FILE, payload)
        if self.best_return is None or result.mean > self.best_return:
            self.best_return = float(result.mean)
            self.best = {**payload, "run": {**payload["run"], "kind": "best"}}
            save_policy(self.path / BEST_POLICY_FILE, self.best)

    def on_interrupt(self, agent: Agent, step: int) -> None:
        """``policy.pt`` with the weights the run stopped with (not evaluated)."""
        save_policy(self.path / POLICY_FILE, self._payload(agent, "interrupted", step, None))

    def state_dict(self) -> dict[str, Any]:
        return {"best_return": self.best_return, "best": self.best}

    def load_state_dict(self, state: dict[str, Any] | None, step: int) -> None:
        """Restore the best policy of a checkpoint at ``step`` and make ``policy_best.pt`` that policy (a
        checkpoint from before policy files leaves a best file only if it is not newer than ``step``)."""
        state = state or {}
        self.best_return, self.best = state.get("best_return"), state.get("best")
        target = self.path / BEST_POLICY_FILE
        if self.best is not None:
            save_policy(target, self.best)
            return
        if target.is_file():
            try:
                import torch

                newer = int(torch.load(target, map_location="cpu", weights_only=True)["run"]["step"]) > step
            except Exception:  # unreadable: not worth keeping either
                newer = True
            if newer:
                log.info("%s is from after the checkpoint at step %d; removed", target, step)
                target.unlink(missing_ok=True)
