"""Small fixtures for tests that need a bound HARS source without an environment."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from mira.replay import ReplayBuffer
from mira.rewards.base import RewardContext
from mira.shaping.config import HarsConfig
from mira.shaping.factors import FactorMeta, FactorSource, FunctionFactorSource
from mira.shaping.source import HarsReward
from mira.tasks.card import TaskCard, load_task


def toy_factors(names: Sequence[str] = ("f_a", "f_b", "f_c"), aux: bool = True) -> FunctionFactorSource:
    """PHI factor ``f_<x>`` reads a distinct, fixed nonlinear function of the observation (by name),
    so that reordering the names reorders the same functions; optional AUX ``u_ctrl = -Σa²``."""

    def make(name: str) -> Callable[[np.ndarray], np.ndarray]:
        h = sum(ord(c) for c in name)

        def fn(obs: np.ndarray) -> np.ndarray:
            d = obs.shape[1]
            return np.tanh(obs[:, h % d]) * (1 + h % 3) + 0.1 * obs[:, (h // 7) % d] ** 2

        return fn

    phi = {n: make(n) for n in names}
    meta = {n: FactorMeta(-5.0, 5.0, "reward" if sum(map(ord, n)) % 2 == 0 else "penalty") for n in names}
    aux_fns = {"u_ctrl": lambda o, a: -np.sum(a * a, axis=-1)} if aux else None
    return FunctionFactorSource(phi, aux_fns, meta)


def make_hars(
    factors: FactorSource | None = None,
    *,
    obs_dim: int = 6,
    act_dim: int = 2,
    capacity: int = 512,
    seed: int = 0,
    gamma: float = 0.99,
    config: HarsConfig | None = None,
    card: TaskCard | None = None,
    background: bool | None = None,
) -> tuple[HarsReward, ReplayBuffer]:
    """A HARS source bound to an empty buffer of ``capacity`` rows (CPU); ``background`` as in
    :class:`HarsReward`."""
    buf = ReplayBuffer(capacity, obs_dim, act_dim)
    src = HarsReward(factors if factors is not None else toy_factors(), config or HarsConfig(),
                     background=background)
    src.bind(RewardContext(card or load_task("halfcheetah", check_env=False), obs_dim, act_dim, gamma,
                           torch.device("cpu"), buf, seed, Path(".")))
    return src, buf


def fill_episodes(src: HarsReward, buf: ReplayBuffer, lengths: Sequence[int], rng: np.random.Generator,
                  terminate: bool = False, sparse: bool = True) -> list[np.ndarray]:
    """Store episodes of consecutive random states (s′_t = s_{t+1}); returns each episode's rows."""
    out = []
    for length in lengths:
        ep = int(buf.episode_id[buf.pos - 1]) + 1 if buf.size else 0
        states = rng.normal(size=(length + 1, buf.obs_dim)).astype(np.float32)
        rewards = rng.normal(size=length).astype(np.float32)
        total = float(rewards.sum())
        for t in range(length):
            last = t == length - 1
            r = (total if last else 0.0) if sparse else float(rewards[t])
            row = buf.add(states[t], rng.uniform(-1, 1, buf.act_dim).astype(np.float32), r, float(rewards[t]),
                          states[t + 1], terminate and last, (not terminate) and last, ep)
            src.on_transition(row)
        rows = buf.finish_episode(total)
        src.on_episode_end(rows, total)
        out.append(rows)
    return out
