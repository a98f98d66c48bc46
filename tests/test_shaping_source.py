"""The HARS reward source: columns, joint gradients, structural edits, checkpoints, monitor helpers."""

from __future__ import annotations

import io
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from mira.agents import make_agent
from mira.agents.base import AgentConfig
from mira.errors import NonFiniteError
from mira.factors.examples import example_program
from mira.rewards.base import RewardContext
from mira.rewards.lookahead import resolve
from mira.shaping.config import HarsConfig
from mira.shaping.factors import ProgramFactorSource, RunningStats
from mira.shaping.source import BASE_LOG_FIELDS, HarsReward
from mira.shaping.testing import fill_episodes, make_hars, toy_factors
from mira.tasks.card import load_task


def _filled(seed: int = 0, config: HarsConfig | None = None, capacity: int = 512,
            names: tuple[str, ...] = ("f_a", "f_b", "f_c"), background: bool | None = None
            ) -> tuple[HarsReward, object, np.random.Generator]:
    # The shaping machinery is tested with the PBRS term on (κ = 1; the default κ is 0).
    config = replace(config or HarsConfig(), shaping_weight=1.0)
    src, buf = make_hars(toy_factors(names), seed=seed, capacity=capacity, config=config, background=background)
    rng = np.random.default_rng(seed)
    fill_episodes(src, buf, [25, 40, 17], rng)
    return src, buf, rng


def _train(src: HarsReward, buf, rng: np.random.Generator, steps: int, batch_size: int = 32) -> list[dict]:
    out = []
    for step in range(steps):
        batch = buf.sample(batch_size, rng)
        src.relabel(batch)
        out.append(src.update(batch, step))
    return out


def test_update_logs_every_field_and_leaves_no_gradients() -> None:
    src, buf, rng = _filled()
    head = ("w_f_a", "w_f_b", "w_f_c", "w_u_ctrl", "w_bias", "share_f_a", "share_f_b", "share_f_c", "share_u_ctrl",
            "decomp_r2", "decomp_loss")
    assert src.log_fields == (*BASE_LOG_FIELDS, "attn_f_a", "attn_f_b", "attn_f_c", *head)
    metrics = _train(src, buf, rng, 3)[-1]
    assert set(metrics) == set(src.log_fields)
    assert all(isinstance(v, torch.Tensor) and v.dim() == 0 and torch.isfinite(v) for v in metrics.values())
    assert float(sum(metrics[f"attn_{n}"] for n in ("f_a", "f_b", "f_c"))) == pytest.approx(1.0, abs=1e-5)
    assert metrics["l_aux"] > 0  # windows of the same episode exist, so the TCE is trained
    assert all(p.grad is None for g in src.nets.opt.param_groups for p in g["params"])


def test_update_changes_fab_vpm_and_tce() -> None:
    src, buf, rng = _filled()
    before = {k: v.clone() for m in (src.nets.fab, src.nets.vpm, src.nets.tce) for k, v in m.state_dict().items()}
    _train(src, buf, rng, 2)
    after = {k: v for m in (src.nets.fab, src.nets.vpm, src.nets.tce) for k, v in m.state_dict().items()}
    changed = [k for k in before if not torch.equal(before[k], after[k])]
    assert any(k.startswith("gru") for k in changed) and any(k.startswith("mlp") for k in changed)
    assert "w_attn" in changed


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_joint_gradient_equals_backprop_through_the_critic(algo: str) -> None:
    """The leaf trick gives exactly ∇(L_RL + λ L_align + ...) w.r.t. (ϕ, φ, ψ)."""
    grads: list[list[torch.Tensor]] = []

    def run(direct: bool) -> None:
        torch.manual_seed(0)
        src, buf, rng = _filled()
        # σ_R = 1 (as before any episode has ended) so that the direct path, which cannot divide by σ_R²,
        # matches.
        src.memory.return_sq = None
        src.nets.weights_changed()
        agent = make_agent(algo, 6, 2, AgentConfig(hidden=(16, 16), batch_size=32), torch.device("cpu"))
        batch = buf.sample(32, rng)
        reward = src.relabel(batch)
        assert reward.requires_grad
        captured: list[torch.Tensor] = []
        params = [p for g in src.nets.opt.param_groups for p in g["params"]]
        src.nets.opt.step = lambda *a, **k: captured.extend(  # type: ignore[method-assign]
            torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in params)
        if direct:  # the naive way: the agent's backward walks a (second) HARS graph into the parameters
            pend = src._pending
            assert pend is not None
            b = batch.reward.shape[0]
            idx = torch.from_numpy(batch.indices)
            f = torch.cat([src.columns.phi[idx], src.columns.phi_next[idx]])
            phi = src.nets.forward(f, torch.cat([batch.obs, batch.next_obs]), src.nets.norm(), n_phi=2 * b)[0]
            agent.update(batch, pend.base + src.gamma * (1 - batch.terminated) * phi[b:] - phi[:b])
            pend.leaf = None
        else:
            agent.update(batch, reward)
        src.update(batch, 0)
        grads.append(captured)

    run(direct=False)
    run(direct=True)
    assert len(grads[0]) == len(grads[1]) > 0
    for a, b in zip(grads[0], grads[1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    assert any(float(g.abs().sum()) > 0 for g in grads[0])


@pytest.mark.parametrize("every", [1, 3])
def test_training_runs_on_every_kth_update_but_phi_is_always_current(every: int) -> None:
    src, buf, rng = _filled(config=HarsConfig(update_every=every))
    params = lambda: [p.detach().clone() for m in (src.nets.fab, src.nets.vpm) for p in m.parameters()]  # noqa: E731
    changed = []
    for step in range(7):
        before = params()
        batch = buf.sample(16, rng)
        reward = src.relabel(batch)
        # The shaped reward uses the current Φ whether or not this batch trains HARS.
        with torch.no_grad():
            fresh = src.relabel(batch)
        torch.testing.assert_close(reward.detach(), fresh)
        assert reward.requires_grad == (step % every == 0)
        metrics = src.update(batch, step)
        assert torch.isfinite(metrics["l_align"])
        src.sync()  # the step may still be running on the training thread
        changed.append(any(not torch.equal(a, b) for a, b in zip(before, params(), strict=True)))
    assert changed == [step % every == 0 for step in range(7)]
    assert src.updates == len(range(0, 7, every)) and src.calls == 7


def test_update_without_relabel_recomputes_the_forward() -> None:
    src, buf, rng = _filled()
    batch = buf.sample(16, rng)
    metrics = src.update(batch, 0)
    assert torch.isfinite(metrics["l_align"])


def test_recompute_all_equals_per_row_values() -> None:
    src, buf, _ = _filled()
    src.columns.flush()  # rows stored since the last batch needed them are evaluated now
    n = buf.size
    cols = [c[:n].clone() for c in (src.columns.phi, src.columns.phi_next, src.columns.aux)]
    running = RunningStats(3)
    running.load_state_dict(src.memory.factor_stats.state_dict())
    for c in (src.columns.phi, src.columns.phi_next, src.columns.aux):
        c.zero_()
    src.columns.recompute_all(7, reset_stats=True)  # small chunks: several passes over the rows
    for before, c in zip(cols, (src.columns.phi, src.columns.phi_next, src.columns.aux), strict=True):
        assert torch.equal(before, c[:n])
    # batch statistics after the reset agree with the per-row running (Welford) ones
    np.testing.assert_allclose(src.memory.factor_stats.mean, running.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(src.memory.factor_stats.var, running.var, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(src.memory.factor_stats.mean, cols[0].double().mean(0).numpy(), rtol=1e-6, atol=1e-6)


def test_set_program_reinitialises_exactly_phi_and_varphi() -> None:
    src, buf, rng = _filled()
    _train(src, buf, rng, 3)
    tce_before = {k: v.clone() for k, v in src.nets.tce.state_dict().items()}
    opt_state = src.nets.opt.state
    tce_opt_before = {id(p): {k: v.clone() for k, v in opt_state[p].items()} for p in src.nets.tce.parameters()}
    phi_before = {k: v.clone() for m in ("fab", "vpm") for k, v in getattr(src.nets, m).state_dict().items()}
    old_fab = src.nets.fab
    new = toy_factors(("f_b", "f_d"))
    src.set_program(new)
    assert src.nets.fab is not old_fab
    for k, v in src.nets.tce.state_dict().items():
        assert torch.equal(v, tce_before[k]), k
    for p in src.nets.tce.parameters():  # ψ keeps its Adam moments
        for k, v in src.nets.opt.state[p].items():
            assert torch.equal(v, tce_opt_before[id(p)][k])
    for p in [*src.nets.fab.parameters(), *src.nets.vpm.parameters()]:  # ϕ, φ start with fresh optimiser state
        assert p not in src.nets.opt.state
    after = {k: v for m in ("fab", "vpm") for k, v in getattr(src.nets, m).state_dict().items()}
    for k, v in after.items():
        assert not torch.equal(v, phi_before[k]), k
    assert src.phi_names == ["f_b", "f_d"] and src.columns.phi.shape[1] == 2
    per_row = new.phi(buf.obs[: buf.size].numpy())
    np.testing.assert_array_equal(src.columns.phi[: buf.size].numpy(), per_row.astype(np.float32))
    metrics = _train(src, buf, rng, 2)[-1]
    assert {"attn_f_b", "attn_f_d"} <= set(metrics)


def test_state_round_trip_resumes_bit_identically() -> None:
    a, buf, rng = _filled(seed=1)
    _train(a, buf, rng, 4)
    with torch.no_grad():
        a.relabel(buf.sample(8, rng))  # Φ's statistics snapshot is taken here ...
    fill_episodes(a, buf, [9], rng)  # ... and the running statistics move on: the checkpoint keeps both
    raw = io.BytesIO()
    torch.save(a.state_dict(), raw)
    raw.seek(0)
    state = torch.load(raw, weights_only=False)

    b, _ = make_hars(toy_factors(), seed=99, capacity=512, config=a.config)  # different init, same buffer below
    b.ctx = a.ctx
    b.load_state_dict(state)
    for x, y in ((a.columns.phi, b.columns.phi), (a.columns.phi_next, b.columns.phi_next),
                 (a.columns.aux, b.columns.aux)):
        assert torch.equal(x[: buf.size], y[: buf.size])
    seq = [buf.sample(32, rng) for _ in range(4)]
    for step, batch in enumerate(seq):
        ma = (a.relabel(batch).detach(), a.update(batch, step))
        mb = (b.relabel(batch).detach(), b.update(batch, step))
        assert torch.equal(ma[0], mb[0])
        assert all(torch.equal(ma[1][k], mb[1][k]) for k in ma[1])
    for ma_, mb_ in ((a.nets.fab, b.nets.fab), (a.nets.vpm, b.nets.vpm), (a.nets.tce, b.nets.tce)):
        for (k, x), (_, y) in zip(ma_.state_dict().items(), mb_.state_dict().items(), strict=True):
            assert torch.equal(x, y), k


def test_monitor_helpers() -> None:
    src, buf, rng = _filled()
    _train(src, buf, rng, 2)
    obs = torch.from_numpy(rng.normal(size=(50, 6)).astype(np.float32))
    phi = src.potential(obs)
    assert phi.shape == (50,) and not phi.requires_grad
    att = src.attention(obs)
    assert list(att) == ["f_a", "f_b", "f_c"] and sum(att.values()) == pytest.approx(1.0)
    # the same factors through the frozen networks: the proxy is the potential itself
    torch.testing.assert_close(src.proxy_potential(toy_factors(), obs), phi, rtol=1e-5, atol=1e-5)
    # a candidate with a new name and a dropped one: frozen networks, finite values, nothing trained
    before = [p.clone() for m in (src.nets.fab, src.nets.vpm) for p in m.parameters()]
    proxy = src.proxy_potential(toy_factors(("f_a", "f_zz")), obs)
    assert proxy.shape == (50,) and torch.isfinite(proxy).all()
    after = [p for m in (src.nets.fab, src.nets.vpm) for p in m.parameters()]
    assert all(torch.equal(x, y) for x, y in zip(before, after, strict=True))
    assert "f_zz" not in src.nets.slots


def test_program_adapter_and_resume_after_an_edit() -> None:
    card = load_task("halfcheetah", check_env=False)
    f0 = ProgramFactorSource(example_program("halfcheetah", 0), card)
    assert f0.phi_names == ["r_vel", "r_upright", "r_stable"] and f0.aux_names == ["r_ctrl"]
    assert (f0.meta["r_vel"].range_lo, f0.meta["r_vel"].range_hi) == (-15.0, 15.0)
    rng = np.random.default_rng(0)

    a, buf = make_hars(f0, obs_dim=17, act_dim=6, card=card)
    fill_episodes(a, buf, [30, 30], rng)
    _train(a, buf, rng, 2)
    a.set_program(ProgramFactorSource(example_program("halfcheetah", 1), card))
    _train(a, buf, rng, 2)
    state = a.state_dict()
    assert state["program"]["factors"] == example_program("halfcheetah", 1).to_json()["factors"]

    b = HarsReward(ProgramFactorSource(example_program("halfcheetah", 0), card), HarsConfig())
    b.bind(RewardContext(card, 17, 6, 0.99, torch.device("cpu"), buf, 0, Path(".")))
    b.load_state_dict(state)  # rebuilds the edited program from the checkpoint
    assert b.phi_names == a.phi_names
    o = torch.from_numpy(rng.normal(size=(10, 17)).astype(np.float32))
    assert torch.equal(a.potential(o), b.potential(o))


def test_factor_columns_are_evaluated_before_anything_reads_them() -> None:
    """Rows are evaluated in batches when needed; every reader sees the same values and statistics as
    if each row had been evaluated when it was stored."""
    lazy, buf, rng = _filled(seed=3)
    eager = HarsReward(toy_factors(), HarsConfig(shaping_weight=1.0))
    eager.bind(lazy.ctx)  # the same buffer (and seed), evaluated row by row below
    # σ_R and the decomposition come from episode ends, not from the rows
    eager.memory.return_sq = lazy.memory.return_sq
    eager.decomposed.head = lazy.head
    eager.decomposed.changed()
    rows = np.arange(buf.size)
    for row in rows:
        eager.on_transition(int(row))
        eager.columns.flush()
    batch = buf.sample(64, rng)
    with torch.no_grad():
        torch.testing.assert_close(lazy.relabel(batch), eager.relabel(batch), rtol=1e-6, atol=1e-6)
    for x, y in ((lazy.columns.phi, eager.columns.phi), (lazy.columns.phi_next, eager.columns.phi_next),
                 (lazy.columns.aux, eager.columns.aux)):
        assert torch.equal(x[: buf.size], y[: buf.size])
    np.testing.assert_allclose(lazy.memory.factor_stats.mean, eager.memory.factor_stats.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(lazy.memory.obs_stats.var, eager.memory.obs_stats.var, rtol=1e-9, atol=1e-12)
    # a stored row is pending until a batch, the statistics, an episode's end (the decomposition head
    # reads the episode's factors) or a checkpoint needs it
    ep = int(buf.episode_id[buf.pos - 1]) + 1
    for _ in range(3):
        state_t = rng.normal(size=buf.obs_dim).astype(np.float32)
        lazy.on_transition(buf.add(state_t, np.zeros(buf.act_dim, np.float32), 0.0, 0.0, state_t, False, False, ep))
    assert len(lazy.columns.pending) == 3
    state = lazy.state_dict()
    assert not lazy.columns.pending and state["columns"]["phi"].shape[0] == buf.size


@pytest.mark.parametrize("every", [1, 4, 8])
def test_lookahead_batches_are_shaped_together_as_they_would_be_one_by_one(every: int) -> None:
    """``lookahead`` counts the updates before the next training step; ``relabel_many`` shapes their
    batches in one pass of Φ with the same result as one relabel per batch; ``revision`` moves exactly
    when the weights that shape batches do: when a training step lands, i.e. when the next training
    batch is shaped (the very first step lands at once)."""
    src, buf, rng = _filled(config=HarsConfig(update_every=every))
    seen = []
    for step in range(2 * every + 1):
        n = src.lookahead()
        seen.append(n)
        batches = [buf.sample(16, rng) for _ in range(n)]
        revision, in_flight = src.revision, src._steps.pending
        rewards = [resolve(r) for r in src.relabel_many(batches)]
        assert len(rewards) == n
        assert (src.revision != revision) == (in_flight and src._trains_now())
        revision = src.revision
        if n > 1:
            with torch.no_grad():
                for b, r in zip(batches, rewards, strict=True):
                    torch.testing.assert_close(r, src.relabel(b), rtol=1e-5, atol=1e-5)
        for b, r in zip(batches, rewards, strict=True):
            trains, first = src._trains_now(), src._last_metrics is None
            src.update(b, step)
            assert (src.revision != revision) == (trains and first)
            revision = src.revision
            assert trains == r.requires_grad  # only a training step's own batch carries a graph
        if src.calls >= 2 * every + 1:
            break
    # the first training batch alone (its step lands at once), then the rest of its cycle, then whole cycles
    expected = [1, 1, 1] if every == 1 else [1, every - 1, every]
    assert seen[: len(expected)] == expected


def test_revision_moves_on_a_new_program_and_on_loaded_state() -> None:
    src = _filled()[0]
    state = src.state_dict()
    revision = src.revision
    src.load_state_dict(state)
    assert src.revision != revision
    revision = src.revision
    src.set_program(toy_factors(("f_a", "f_d")))
    assert src.revision != revision


@pytest.mark.parametrize(("cores", "threads", "load", "setting", "expected"), [
    (2, 1, 0.2, None, True), (2, 2, 0.2, None, False), (8, 4, 0.2, None, True), (1, 1, 0.0, None, False),
    (1, 1, 0.0, True, True), (8, 1, 0.0, False, False),
    # Another run on the machine takes the core the thread would use; on 8 cores there is room still.
    (2, 1, 1.2, None, False), (2, 1, 2.0, None, False), (8, 1, 2.0, None, True), (2, 1, 0.2, True, True)])
def test_background_training_by_default_only_with_a_spare_core(monkeypatch: pytest.MonkeyPatch, cores: int,
                                                               threads: int, load: float, setting: bool | None,
                                                               expected: bool) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    src = HarsReward(toy_factors(), HarsConfig(), background=setting)
    assert src.background is expected
    assert src.describe()["train_in_background"] is expected


@pytest.mark.parametrize("background", [False, True])
def test_a_non_finite_training_step_stops_the_run_before_its_weights_are_used(background: bool) -> None:
    src, buf, rng = _filled(config=HarsConfig(update_every=2), background=background)
    for step in range(2):  # the first step lands at once; the second update does not train
        batch = buf.sample(16, rng)
        src.relabel(batch)
        src.update(batch, step)
    with torch.no_grad():
        src.nets.vpm.mlp[-1].bias.fill_(float("nan"))  # Φ is NaN from here on
    batch = buf.sample(16, rng)
    src.relabel(batch)
    metrics = src.update(batch, 2)  # the step is launched; the figures are the last landed step's
    assert all(bool(torch.isfinite(v)) for v in metrics.values())
    with pytest.raises(NonFiniteError, match=r"HARS training step 2 .*non-finite .*l_align"):
        src.state_dict()  # a checkpoint lands the step first, and refuses it
