from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import distributions as D

from mira.agents import AgentConfig, make_agent
from mira.agents.networks import EnsembleQ, SquashedGaussianActor
from mira.replay import ReplayBuffer


def test_ensemble_q_matches_member_by_member() -> None:
    torch.manual_seed(0)
    q = EnsembleQ(2, 5, 3, (16, 16))
    obs, act = torch.randn(7, 5), torch.randn(7, 3)
    out = q(obs, act)
    x = torch.cat((obs, act), -1)
    for e in range(2):
        h = x
        for i, layer in enumerate(q.layers):
            h = h @ layer.weight[e] + layer.bias[e]
            if i < len(q.layers) - 1:
                h = torch.relu(h)
        assert torch.allclose(out[e], h.squeeze(-1), atol=1e-5)


def test_squashed_log_prob_matches_torch_distributions() -> None:
    torch.manual_seed(0)
    actor = SquashedGaussianActor(4, 3, (16, 16))
    obs = torch.randn(32, 4)
    torch.manual_seed(1)
    action, logp = actor.sample(obs)
    mean, log_std = actor.distribution(obs)
    dist = D.TransformedDistribution(D.Normal(mean, log_std.exp()), [D.TanhTransform(cache_size=1)])
    clipped = action.clamp(-1 + 1e-6, 1 - 1e-6)
    ref = dist.log_prob(clipped).sum(-1)
    assert torch.allclose(logp, ref, atol=1e-2)
    assert action.abs().max() <= 1.0


def _buffer(obs_dim: int = 6, act_dim: int = 2) -> ReplayBuffer:
    buf = ReplayBuffer(500, obs_dim, act_dim)
    rng = np.random.default_rng(0)
    for t in range(300):
        buf.add(rng.normal(size=obs_dim), rng.uniform(-1, 1, act_dim), rng.normal(), 0.0, rng.normal(size=obs_dim),
                bool(t % 50 == 49), False, t // 50)
    return buf


@pytest.mark.parametrize("kernels", ["fused", "plain"])
@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_update_moves_parameters_and_state_round_trips(algo: str, kernels: str) -> None:
    torch.manual_seed(0)
    cfg = AgentConfig(hidden=(32, 32), batch_size=32, lr=1e-3, kernels=kernels)
    agent = make_agent(algo, 6, 2, cfg, torch.device("cpu"))
    before = [p.detach().clone() for p in agent.actor.parameters()]  # type: ignore[attr-defined]
    buf, rng = _buffer(), np.random.default_rng(0)
    for _ in range(5):
        batch = buf.sample(32, rng)
        metrics = agent.update(batch, batch.reward)
    assert all(math.isfinite(float(v)) for v in metrics.values())
    after = list(agent.actor.parameters())  # type: ignore[attr-defined]
    assert any(not torch.equal(b, a) for b, a in zip(before, after, strict=True))
    clone = make_agent(algo, 6, 2, cfg, torch.device("cpu"))
    clone.load_state_dict(agent.state_dict())
    obs = np.random.default_rng(2).normal(size=6)
    assert np.allclose(clone.act(obs, deterministic=True), agent.act(obs, deterministic=True))
    stats = agent.policy_stats(torch.as_tensor(np.zeros((4, 6)), dtype=torch.float32))
    assert stats.mean.shape == (4, 2) and stats.squashed == (algo == "sac")


def test_reward_gradient_flows_through_critic_loss() -> None:
    """A reward that requires grad (HARS's joint mode) receives the critic loss's gradient."""
    torch.manual_seed(0)
    agent = make_agent("sac", 6, 2, AgentConfig(hidden=(16, 16), batch_size=16), torch.device("cpu"))
    batch = _buffer().sample(16, np.random.default_rng(0))
    reward = batch.reward.clone().requires_grad_(True)
    agent.update(batch, reward)
    assert reward.grad is not None and reward.grad.abs().sum() > 0


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_fused_and_plain_updates_agree(algo: str) -> None:
    """``kernels="fused"`` (explicit backward formulas, fused Adam) computes the plain autograd update:
    after several updates from the same start, with the same batches and random draws, every
    parameter, the temperature and the reported figures agree up to float rounding."""
    agents, figures = [], []
    for kernels in ("fused", "plain"):
        torch.manual_seed(0)
        cfg = AgentConfig(hidden=(32, 32), batch_size=32, lr=1e-3, kernels=kernels)
        agent = make_agent(algo, 6, 2, cfg, torch.device("cpu"))
        buf, rng = _buffer(), np.random.default_rng(0)
        torch.manual_seed(1)
        for _ in range(6):
            batch = buf.sample(32, rng)
            reward = batch.reward.clone().requires_grad_(True)
            metrics = agent.update(batch, reward)
        agents.append(agent)
        figures.append((metrics, reward.grad))
    fused, plain = (a.state_dict() for a in agents)
    for part in ("actor", "critic", "critic_target"):
        for key, value in fused[part].items():
            torch.testing.assert_close(value, plain[part][key], rtol=1e-4, atol=1e-5, msg=f"{part}.{key}")
    if algo == "sac":
        torch.testing.assert_close(fused["log_alpha"], plain["log_alpha"], rtol=1e-4, atol=1e-6)
    assert set(figures[0][0]) == set(figures[1][0])
    for key, value in figures[0][0].items():
        torch.testing.assert_close(value, figures[1][0][key], rtol=1e-4, atol=1e-5, msg=key)
    torch.testing.assert_close(figures[0][1], figures[1][1], rtol=1e-4, atol=1e-6)  # the reward's gradient


def test_unknown_kernels_are_refused() -> None:
    with pytest.raises(ValueError, match=r"agent\.kernels"):
        make_agent("sac", 6, 2, AgentConfig(kernels="fast"), torch.device("cpu"))


def test_a_pytorch_without_the_fused_path_internals_falls_back_to_the_plain_update(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Where the start-up self-test finds an internal missing or changed, the agent runs the plain autograd
    update, says so once, and still learns; where it finds none, the fused path is kept."""
    import mira.agents as agents

    assert agents.fused_path_problem() is None  # this PyTorch runs the fused path
    monkeypatch.setattr(agents, "fused_path_problem", lambda: "torch._fused_adam_ is missing")
    with caplog.at_level("WARNING", logger="mira.agents"):
        agent = make_agent("sac", 6, 2, AgentConfig(hidden=(32, 32), batch_size=32), torch.device("cpu"))
    assert agent.config.kernels == "plain"  # type: ignore[attr-defined]
    assert "plain autograd update" in caplog.text and "_fused_adam_" in caplog.text
    buf, rng = _buffer(), np.random.default_rng(0)
    batch = buf.sample(32, rng)
    assert all(math.isfinite(float(v)) for v in agent.update(batch, batch.reward).values())


def test_polyak_averaging_works_without_foreach_lerp(monkeypatch: pytest.MonkeyPatch) -> None:
    from mira.agents import torch_private as tp

    monkeypatch.delattr(torch, "_foreach_lerp_")
    a, b = [torch.ones(3)], [torch.full((3,), 3.0)]
    tp.foreach_lerp_(a, b, 0.25)
    torch.testing.assert_close(a[0], torch.full((3,), 1.5))


def test_the_fused_path_self_test_leaves_the_global_generator_alone() -> None:
    """It runs inside the first make_agent of a process: drawing from the global generator there would make
    a run's first agent differ from every later one of the same seed."""
    from mira.agents import torch_private as tp

    tp.fused_path_problem.cache_clear()
    torch.manual_seed(3)
    before = torch.get_rng_state()
    assert tp.fused_path_problem() is None
    assert torch.equal(before, torch.get_rng_state())
