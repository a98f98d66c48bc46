from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mira.replay import ReplayBuffer


def _fill(buf: ReplayBuffer, lengths: list[int]) -> list[float]:
    returns = []
    for ep, n in enumerate(lengths):
        for t in range(n):
            buf.add(np.full(3, t), np.zeros(2), 0.0, 1.0, np.full(3, t + 1), False, t == n - 1, ep)
        returns.append(float(ep * 10))
        buf.finish_episode(returns[-1])
    return returns


def test_episode_returns_are_written_next_to_transitions() -> None:
    buf = ReplayBuffer(100, 3, 2)
    _fill(buf, [5, 7])
    assert torch.all(buf.episode_return[:5] == 0.0)
    assert torch.all(buf.episode_return[5:12] == 10.0)
    assert buf.episode_step[5:12].tolist() == list(range(7))


def test_completed_only_never_samples_the_open_episode() -> None:
    buf = ReplayBuffer(100, 3, 2)
    _fill(buf, [4])
    for _ in range(6):
        buf.add(np.zeros(3), np.zeros(2), 0.0, 0.0, np.zeros(3), False, False, 1)
    idx = buf.sample_indices(1000, np.random.default_rng(0), completed_only=True)
    assert set(idx.tolist()) == {0, 1, 2, 3}
    assert not torch.isnan(buf.gather(idx).episode_return).any()


@settings(max_examples=40, deadline=None)
@given(lengths=st.lists(st.integers(1, 9), min_size=1, max_size=12), capacity=st.integers(3, 30),
       open_len=st.integers(0, 5))
def test_ring_buffer_sampling_and_round_trip(lengths: list[int], capacity: int, open_len: int) -> None:
    buf = ReplayBuffer(capacity, 3, 2)
    _fill(buf, lengths)
    for _ in range(open_len):
        buf.add(np.ones(3), np.zeros(2), 0.0, 0.0, np.ones(3), False, False, 99)
    assert buf.size == min(capacity, sum(lengths) + open_len)
    if buf.completed_size > 0:
        batch = buf.sample(64, np.random.default_rng(1), completed_only=True)
        assert not torch.isnan(batch.episode_return).any()
        assert not (batch.episode_id == 99).any()
    clone = ReplayBuffer(capacity, 3, 2)
    clone.load_state_dict(buf.state_dict())
    for col in ("obs", "action", "episode_id", "episode_return"):
        a, b = getattr(buf, col)[: buf.size], getattr(clone, col)[: buf.size]
        assert torch.equal(torch.nan_to_num(a, nan=-7), torch.nan_to_num(b, nan=-7))
    assert (clone.pos, clone.open_episode_len) == (buf.pos, buf.open_episode_len)
