"""Policy files: a trained actor, small and self-describing, to use without the run that made it.

Every run writes ``RUN_DIR/policy.pt`` (the policy at its latest evaluation, and at the end of the run)
and ``RUN_DIR/policy_best.pt`` (the policy of its best evaluation so far). A policy file is a
``torch.save`` of plain data only (tensors, dicts, lists, str, int, float, bool, None), so that
``torch.load(path, weights_only=True)`` reads it without running any code from the file:

=====================  =========================================================================
key                    what
=====================  =========================================================================
``format``             ``"mira-policy"``; ``version``: 1
``algo``               ``"sac"`` (squashed Gaussian actor) or ``"ddpg"`` (deterministic actor)
``obs_dim``            observation size; ``act_dim``: action size
``hidden``             the hidden widths of the actor's MLP; ``activation``: ``"relu"``
``actor``              the actor's ``state_dict`` (:class:`~mira.agents.networks.SquashedGaussianActor`
                       or :class:`~mira.agents.networks.DeterministicActor`)
``action_low/high``    the environment's own action bounds (float tensors): the actor acts in
                       [-1, 1] and :meth:`Policy.predict` maps that onto them as training did
                       (``action_rescaled``: whether the environment's bounds differ from [-1, 1])
``exploration_noise``  DDPG: the std of the Gaussian noise of a non-deterministic action
``obs_norm``           None, or ``{"mean", "std", "clip"}`` applied to observations first
``task``               ``name``, ``env_id``, ``env_kwargs`` (JSON text), ``max_episode_steps`` (None:
                       the environment's own), ``card`` (the task card as JSON text), ``source`` (the
                       card file it came from, if any)
``run``                ``kind`` (``"latest"``, ``"final"``, ``"best"``, ``"interrupted"``), ``step``,
                       ``seed``, ``method``, ``eval_seed_base`` and ``eval_episodes`` (the seeds and
                       number of the run's evaluation episodes), ``eval_return_mean``/``_std`` (the
                       evaluation of these weights; None if they were never evaluated)
``mira_version``       the version that wrote it
=====================  =========================================================================

No replay buffer, critic or optimiser state: ``RUN_DIR/checkpoints/`` keeps those for ``--resume``.
"""

from __future__ import annotations

import io
import json
import math
import os
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from mira.agents.networks import (
    _LOG_STD_HALF,
    _LOG_STD_MID,
    DeterministicActor,
    SquashedGaussianActor,
    relu_mlp,
    relu_mlp_1d,
)
from mira.errors import UsageError
from mira.runio.atomic import atomic_write_bytes

FORMAT = "mira-policy"
VERSION = 1
POLICY_FILE = "policy.pt"
BEST_POLICY_FILE = "policy_best.pt"


class PolicyFileError(UsageError):
    """A policy file is missing, unreadable or not a MIRA policy."""


def policy_payload(*, algo: str, obs_dim: int, act_dim: int, hidden: tuple[int, ...],
                   actor_state: dict[str, torch.Tensor], action_space: gym.spaces.Box,
                   exploration_noise: float, task: dict[str, Any], run: dict[str, Any],
                   obs_norm: dict[str, Any] | None = None) -> dict[str, Any]:
    """The policy file's content (see the module docstring): plain data and CPU tensors only."""
    from mira.version import __version__

    low = torch.as_tensor(np.asarray(action_space.low), dtype=torch.float32)
    high = torch.as_tensor(np.asarray(action_space.high), dtype=torch.float32)
    return {
        "format": FORMAT, "version": VERSION, "algo": algo, "obs_dim": int(obs_dim), "act_dim": int(act_dim),
        "hidden": [int(w) for w in hidden], "activation": "relu",
        "actor": {k: v.detach().to("cpu", copy=True) for k, v in actor_state.items()},
        "action_low": low, "action_high": high, "action_dtype": str(np.dtype(action_space.dtype)),
        "action_rescaled": not (bool(torch.all(low == -1.0)) and bool(torch.all(high == 1.0))),
        "exploration_noise": float(exploration_noise), "obs_norm": obs_norm,
        "task": dict(task), "run": dict(run), "mira_version": __version__,
    }


def save_policy(path: str | os.PathLike[str], payload: dict[str, Any]) -> Path:
    """Write a policy file atomically (the previous one stays whole until the new one is complete)."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def resolve_policy_path(target: str | os.PathLike[str], best: bool = False) -> Path:
    """``target`` itself when it is a file, else the run directory's ``policy.pt`` (``policy_best.pt``
    with ``best``)."""
    path = Path(target)
    if path.is_dir():
        name = BEST_POLICY_FILE if best else POLICY_FILE
        found = path / name
        if not found.is_file():
            hint = (" (the run has not evaluated yet, or predates policy files; its checkpoints still resume "
                    "it)") if (path / "config.json").is_file() else " (not a run directory)"
            raise PolicyFileError(f"{path}: no {name}{hint}")
        return found
    if not path.is_file():
        raise PolicyFileError(f"{path}: no such policy file or run directory")
    if best:
        raise PolicyFileError(f"{path}: --best/best=True picks policy_best.pt of a run directory; "
                              "name the run directory, or the file itself without it")
    return path


class Policy:
    """A trained actor rebuilt from a policy file: ``predict`` turns observations into actions.

    >>> policy = Policy.load("runs/hc-dense")          # RUN_DIR/policy.pt, or a policy file
    >>> env = policy.make_env()                         # the task's Gymnasium environment, as trained
    >>> obs, _ = env.reset(seed=0)
    >>> action = policy.predict(obs)                    # in the environment's own action bounds
    """

    def __init__(self, payload: dict[str, Any], path: Path | None = None) -> None:
        _check_payload(payload, path)
        self.path = path
        self.algo: str = payload["algo"]
        self.obs_dim: int = int(payload["obs_dim"])
        self.act_dim: int = int(payload["act_dim"])
        self.hidden: tuple[int, ...] = tuple(int(w) for w in payload["hidden"])
        self.task: dict[str, Any] = dict(payload["task"])
        self.run: dict[str, Any] = dict(payload["run"])
        self.exploration_noise = float(payload.get("exploration_noise", 0.0))
        kind = SquashedGaussianActor if self.algo == "sac" else DeterministicActor
        self.actor: SquashedGaussianActor | DeterministicActor = kind(self.obs_dim, self.act_dim, self.hidden)
        try:
            self.actor.load_state_dict(payload["actor"])
        except RuntimeError as exc:
            raise PolicyFileError(f"{path or 'policy'}: the actor's weights do not fit its description ({exc})") \
                from None
        self.actor.eval().requires_grad_(False)
        self._params: list[torch.Tensor] = self.actor.params()
        dtype = np.dtype(payload.get("action_dtype", "float32"))
        low, high = payload["action_low"].numpy().astype(dtype), payload["action_high"].numpy().astype(dtype)
        self.action_space = gym.spaces.Box(low, high, dtype=dtype)
        self._to_env = _rescaler(self.action_space) if payload.get("action_rescaled") else None
        norm = payload.get("obs_norm")
        self._obs_norm = None if norm is None else (norm["mean"].float(), norm["std"].float(), norm.get("clip"))
        self.payload = payload

    # ------------------------------------------------------------------------------- loading
    @classmethod
    def load(cls, path: str | os.PathLike[str], best: bool = False) -> Policy:
        """A policy file, or a run directory's ``policy.pt`` (``policy_best.pt`` with ``best``)."""
        file = resolve_policy_path(path, best)
        try:
            payload = torch.load(file, map_location="cpu", weights_only=True)
        except Exception as exc:  # the unpickler refuses anything but plain data, with varied errors
            raise PolicyFileError(f"{file}: not a readable policy file ({type(exc).__name__}: {exc})") from None
        return cls(payload, file)

    # ------------------------------------------------------------------------------- acting
    @torch.inference_mode()
    def act(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The actor's action in [-1, 1]^A (what the trainer stores and evaluates), for one observation
        ``[obs_dim]`` or a batch ``[B, obs_dim]``. A single observation goes through the same
        matrix-vector products as acting during training, so a deterministic episode repeats the run's
        evaluation exactly."""
        x = torch.as_tensor(np.asarray(obs), dtype=torch.float32)
        if x.shape[-1] != self.obs_dim or x.ndim not in (1, 2):
            raise ValueError(f"expected an observation of shape [{self.obs_dim}] or [B, {self.obs_dim}], "
                             f"got {tuple(x.shape)}")
        if self._obs_norm is not None:
            mean, std, clip = self._obs_norm
            x = (x - mean) / std
            if clip is not None:
                x = x.clamp(-float(clip), float(clip))
        out = relu_mlp_1d(self._params, x) if x.ndim == 1 else relu_mlp(self._params, x)
        if self.algo == "sac":
            mean_a, raw = out.chunk(2, dim=-1)
            if deterministic:
                return torch.tanh(mean_a).numpy()
            std_a = torch.tanh(raw).mul_(_LOG_STD_HALF).add_(_LOG_STD_MID).exp_()
            return torch.tanh(torch.addcmul(mean_a, std_a, torch.randn_like(mean_a))).numpy()
        action = torch.tanh(out)
        if not deterministic:
            action = (action + self.exploration_noise * torch.randn_like(action)).clamp_(-1.0, 1.0)
        return action.numpy()

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """Actions in the environment's own action space for one observation or a batch (like
        Stable-Baselines3's ``predict``, but the action alone, not an ``(action, state)`` pair).
        ``deterministic=False`` samples as the policy explored in training (SAC's Gaussian, DDPG's
        noise; torch's random generator)."""
        action = self.act(obs, deterministic)
        return action if self._to_env is None else np.asarray(self._to_env(action), dtype=self.action_space.dtype)

    # -------------------------------------------------------------------------- environment
    @property
    def env_id(self) -> str:
        return str(self.task["env_id"])

    @property
    def env_kwargs(self) -> dict[str, Any]:
        kwargs: dict[str, Any] = json.loads(self.task.get("env_kwargs") or "{}")
        return kwargs

    def make_env(self, **kwargs: Any) -> gym.Env[Any, Any]:
        """The task's environment as the run trained on it (its ``env_kwargs`` and time limit), with the
        environment's own action space, which :meth:`predict` answers in. ``kwargs`` go to
        ``gymnasium.make`` (e.g. ``render_mode="rgb_array"``)."""
        from mira.tasks.card import import_env_module

        env_id = import_env_module(self.env_id, self.task.get("source"))
        options = {**self.env_kwargs, **kwargs}
        if self.task.get("max_episode_steps") is not None:
            options.setdefault("max_episode_steps", int(self.task["max_episode_steps"]))
        return gym.make(env_id, **options)

    def describe(self) -> str:
        """One line: what, trained on what, at which step, with which evaluation."""
        r = self.run
        ev = r.get("eval_return_mean")
        figure = "" if ev is None or not math.isfinite(float(ev)) else \
            f", evaluated at {float(ev):.2f} ± {float(r.get('eval_return_std') or 0.0):.2f}"
        return (f"{self.algo.upper()} policy for {self.task.get('name')} ({self.env_id}), {r.get('method', '?')} "
                f"seed {r.get('seed', '?')}, {r.get('kind', '?')} at step {r.get('step', '?')}{figure}")

    def __repr__(self) -> str:
        return f"Policy({self.describe()})"


def load_policy(path: str | os.PathLike[str], best: bool = False) -> Policy:
    """:meth:`Policy.load`: a policy file, or a run directory's ``policy.pt`` (``policy_best.pt``
    with ``best``)."""
    return Policy.load(path, best)


def _rescaler(space: gym.spaces.Box) -> Any:
    """The map from [-1, 1] onto ``space`` that ``gymnasium.wrappers.RescaleAction`` applies in
    training (the same function, so the same float arithmetic)."""
    from gymnasium.wrappers.utils import rescale_box

    ones = np.ones(space.shape, dtype=space.dtype)
    _, _, to_env = rescale_box(space, -ones, ones)  # (new space, to it, from it): the wrapper applies the last
    return to_env


def _check_payload(payload: Any, path: Path | None) -> None:
    where = str(path) if path is not None else "policy"
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise PolicyFileError(f"{where}: not a MIRA policy file (no format {FORMAT!r}); a checkpoint "
                              "(checkpoints/ckpt-*.pt) resumes training, it is not a policy file")
    if int(payload.get("version", 0)) > VERSION:
        raise PolicyFileError(f"{where}: policy file version {payload.get('version')} is newer than this "
                              f"mira reads ({VERSION}); upgrade mira")
    missing = [k for k in ("algo", "obs_dim", "act_dim", "hidden", "actor", "action_low", "action_high", "task",
                           "run") if k not in payload]
    if missing:
        raise PolicyFileError(f"{where}: policy file lacks {', '.join(missing)}")
    if payload["algo"] not in ("sac", "ddpg"):
        raise PolicyFileError(f"{where}: unknown algo {payload['algo']!r}")
