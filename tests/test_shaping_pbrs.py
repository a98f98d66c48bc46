"""PBRS with absorbing terminals: shaped returns telescope for any potential."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mira.shaping import objective
from mira.shaping.config import HarsConfig
from mira.shaping.testing import fill_episodes, make_hars, toy_factors

EPISODIC = HarsConfig(alignment="episodic")
"""The paper's letter: r_ext + γΦ(s′) − Φ(s), the PBRS term on the reward these tests can check by hand."""


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    length=st.integers(1, 40),
    gamma=st.floats(0.5, 1.0),
    terminate=st.booleans(),
    scale=st.floats(0.01, 100.0),
    sparse=st.booleans(),
)
def test_discounted_shaped_return_telescopes(seed: int, length: int, gamma: float, terminate: bool,
                                             scale: float, sparse: bool) -> None:
    src, buf = make_hars(toy_factors(), seed=seed, gamma=gamma, capacity=64,
                         config=EPISODIC)
    with torch.no_grad():  # an arbitrary potential: random network, random output scale and offset
        last = src.nets.vpm.mlp[-1]
        last.weight.mul_(scale)
        last.bias.add_(scale * (seed % 7 - 3))
    rng = np.random.default_rng(seed)
    fill_episodes(src, buf, [3], rng)  # some history first (statistics, other rows)
    (rows,) = fill_episodes(src, buf, [length], rng, terminate=terminate, sparse=sparse)
    batch = buf.gather(rows)
    with torch.no_grad():
        shaped = src.relabel(batch).double().numpy()
    disc = gamma ** np.arange(length)
    extrinsic = float((disc * batch.reward.double().numpy()).sum())
    phi0 = float(src.potential(batch.obs[:1])[0])
    phi_t = float(src.potential(batch.next_obs[-1:])[0])
    expected = extrinsic - phi0 + (0.0 if terminate else gamma**length * phi_t)
    tol = 1e-4 * (1.0 + abs(phi0) + abs(phi_t) + np.abs(shaped).sum())
    assert abs(float((disc * shaped).sum()) - expected) <= tol


def test_terminal_next_state_has_zero_potential_but_truncation_keeps_it() -> None:
    src, buf = make_hars(toy_factors(), config=EPISODIC)
    rng = np.random.default_rng(0)
    (term_rows,) = fill_episodes(src, buf, [5], rng, terminate=True)
    (trunc_rows,) = fill_episodes(src, buf, [5], rng, terminate=False)
    with torch.no_grad():
        for rows, terminal in ((term_rows, True), (trunc_rows, False)):
            batch = buf.gather(rows[-1:])
            shaped = src.relabel(batch)
            phi_s, phi_next = src.potential(batch.obs), src.potential(batch.next_obs)
            assert float(phi_next.abs()) > 0  # the potential of s' itself is not zero
            want = batch.reward - phi_s + (0.0 if terminal else src.gamma * phi_next)
            torch.testing.assert_close(shaped, want, rtol=1e-5, atol=1e-5)


def test_relabel_uses_the_current_potential() -> None:
    src, buf = make_hars(toy_factors(), config=EPISODIC)
    rng = np.random.default_rng(0)
    fill_episodes(src, buf, [30], rng)
    batch = buf.sample(16, rng)
    with torch.no_grad():
        before = src.relabel(batch)
        src.nets.vpm.mlp[-1].bias.add_(1.0)  # Φ ← Φ + σ_R: shaped reward moves by σ_R (γ·(1 − d) − 1)
        src.weights_changed()  # an edit outside ``update`` says so (the shaping caches derived tensors)
        after = src.relabel(batch)
    unit = src.memory.phi_scale
    assert unit > 1.0  # the episode's return set the unit Φ is learned in
    torch.testing.assert_close(after - before, unit * (src.gamma * (1 - batch.terminated) - 1.0), rtol=1e-4,
                               atol=1e-4)


def test_relabel_after_a_training_step_uses_the_new_weights_and_statistics() -> None:
    """Between two HARS training steps Φ is one fixed function (weights and input statistics); after a
    step the shaping of any batch is the updated modules' own Φ, not a stale cached one."""
    # σ_R moves too
    src, buf = make_hars(toy_factors(), config=HarsConfig(lr=1e-2, update_every=1, alignment="episodic"))
    rng = np.random.default_rng(1)
    fill_episodes(src, buf, [40], rng)
    batch, probe = buf.sample(32, rng), buf.sample(16, rng)
    with torch.no_grad():
        before = src.relabel(probe)
    fill_episodes(src, buf, [40], rng)  # the running statistics move
    with torch.no_grad():
        assert torch.equal(src.relabel(probe), before)  # no training step: the same Φ
    src.relabel(batch)
    src.update(batch, 0)
    with torch.no_grad():
        after = src.relabel(probe)
        b = probe.reward.shape[0]
        rows = torch.from_numpy(probe.indices)
        f = torch.cat([src.columns.phi[rows], src.columns.phi_next[rows]])
        norm = src.nets.norm()
        snap = src.nets.snapshot
        assert snap is not None and np.array_equal(snap.f_mean, src.memory.factor_stats.mean)  # fresh
        phi = src.nets.forward(f, torch.cat([probe.obs, probe.next_obs]), norm)[0]
    want = probe.reward + src.gamma * (1 - probe.terminated) * phi[b:] - phi[:b]
    torch.testing.assert_close(after, want, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(after, before)


def test_terminal_penalty_pulls_terminal_potential_to_zero(monkeypatch: pytest.MonkeyPatch) -> None:
    # The terminal penalty alone beside L_align: no auxiliary or entropy term.
    monkeypatch.setattr(objective, "AUX_WEIGHT", 0.0)
    monkeypatch.setattr(objective, "ENTROPY_WEIGHT", 0.0)

    def final_terminal_phi_sq(eta: float) -> float:
        monkeypatch.setattr(objective, "TERMINAL_WEIGHT", eta)
        src, buf = make_hars(toy_factors(), config=HarsConfig(lr=3e-3))
        rng = np.random.default_rng(0)
        rows = [r[-1] for r in fill_episodes(src, buf, [4] * 8, rng, terminate=True)]
        batch = buf.gather(np.asarray(rows))
        for step in range(100):
            src.relabel(batch)
            src.update(batch, step)
        return float(src.potential(batch.next_obs).pow(2).mean())

    assert final_terminal_phi_sq(10.0) < 0.2 * final_terminal_phi_sq(0.0)
