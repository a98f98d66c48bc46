"""Episodes as row ranges of the replay buffer: storage, ring-buffer overwrite, subsequence sampling."""

from __future__ import annotations

import numpy as np
import pytest

from mira.replay import ReplayBuffer
from mira.rewards.episodes import EpisodeStore


def _episode(buf: ReplayBuffer, store: EpisodeStore, length: int, ret: float, ep: int) -> np.ndarray:
    for t in range(length):
        buf.add(np.full(3, ep, dtype=np.float32), np.zeros(2), 0.0, 0.0, np.zeros(3), False, t == length - 1, ep)
    rows = buf.finish_episode(ret)
    store.add(rows, ret)
    return rows


def test_store_prunes_overwritten_episodes_in_order() -> None:
    buf = ReplayBuffer(100, 3, 2)
    store = EpisodeStore(buf)
    for ep in range(3):
        _episode(buf, store, 30, float(ep), ep)
    assert len(store) == 3 and store.n_intact() == 3
    _episode(buf, store, 30, 3.0, 3)  # 120 rows written: episode 0 lost its first 20 rows
    assert len(store) == 4 and store.intact_start() == 1 and store.n_intact() == 3
    assert store.prune() == 0 and list(store.returns) == [0.0, 1.0, 2.0, 3.0]  # episode 0 still has rows in the buffer
    _episode(buf, store, 30, 4.0, 4)  # 150 rows: episode 0 is gone entirely, episode 1 partly
    assert list(store.returns) == [1.0, 2.0, 3.0, 4.0]
    assert store.intact_start() == 1
    rng = np.random.default_rng(0)
    for i in store.sample(50, rng):
        assert i >= store.intact_start()


def test_step_rows_stay_inside_their_episode() -> None:
    buf = ReplayBuffer(64, 3, 2)
    store = EpisodeStore(buf)
    lengths = [7, 13, 20, 5, 9, 11, 17]  # 82 rows: the ring wraps
    for ep, n in enumerate(lengths):
        _episode(buf, store, n, float(ep), ep)
    rng = np.random.default_rng(1)
    idx = store.sample(40, rng)
    episode_of = {k: int(buf.episode_id[int(store.start_rows(np.array([k]))[0])]) for k in range(len(store))}
    for subseq in (4, None):
        rows, mask = store.step_rows(idx, rng, subseq)
        for e, k in enumerate(idx):
            valid = rows[e][mask[e]]
            n = int(store.length[k])
            assert len(valid) == (n if subseq is None else min(n, subseq))
            assert len(set(valid.tolist())) == len(valid)  # without replacement
            assert np.all(buf.episode_id[valid].numpy() == episode_of[int(k)])
            if subseq is None:
                assert sorted(buf.episode_step[valid].tolist()) == list(range(n))


def test_episode_longer_than_buffer_is_not_stored() -> None:
    buf = ReplayBuffer(10, 3, 2)
    store = EpisodeStore(buf)
    _episode(buf, store, 25, 1.0, 0)
    assert len(store) == 0 and store.rejected == 1
    _episode(buf, store, 4, 2.0, 1)
    assert len(store) == 1 and store.n_intact() == 1


def test_store_state_round_trip_and_bound() -> None:
    buf = ReplayBuffer(1000, 3, 2)
    store = EpisodeStore(buf, max_episodes=3)
    for ep in range(5):
        _episode(buf, store, 10, float(ep), ep)
    assert list(store.returns) == [2.0, 3.0, 4.0]
    other = EpisodeStore(buf, max_episodes=3)
    other.load_state_dict(store.state_dict())
    assert np.array_equal(other.first, store.first) and np.array_equal(other.returns, store.returns)
    with pytest.raises(ValueError):
        EpisodeStore(buf, max_episodes=0)
