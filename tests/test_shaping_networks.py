"""HARS networks: the factor attention is a set function keyed by names, masking is dropping, the TCE
ignores padding."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mira.shaping.factors import META_DIM
from mira.shaping.networks import (
    FactorAttentionBlock,
    FrozenPotential,
    TemporalContextEncoder,
    ValuePotential,
    attention_entropy,
)
from mira.shaping.testing import fill_episodes, make_hars, toy_factors

OBS = 7


def _fab(seed: int = 0) -> FactorAttentionBlock:
    torch.manual_seed(seed)
    return FactorAttentionBlock(OBS, d_z=16, id_dim=8, id_slots=16, hidden=16, query_hidden=16)


def _inputs(b: int, k: int, seed: int = 1) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(b, k, generator=g), torch.randn(b, OBS, generator=g), torch.randn(k, 8, generator=g),
            torch.randn(k, META_DIM, generator=g))


@pytest.mark.parametrize("k", [1, 2, 5, 12, 16])
def test_attention_is_permutation_invariant(k: int) -> None:
    fab = _fab()
    x, obs, ids, meta = _inputs(9, k)
    v, alpha = fab(x, obs, ids, meta)
    perm = torch.randperm(k, generator=torch.Generator().manual_seed(k))
    v_p, alpha_p = fab(x[:, perm], obs, ids[perm], meta[perm])
    torch.testing.assert_close(v_p, v, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(alpha_p, alpha[:, perm], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(alpha.sum(-1), torch.ones(9))
    assert torch.isfinite(attention_entropy(alpha)).all()


@settings(max_examples=40, deadline=None)
@given(k=st.integers(0, 12), b=st.integers(1, 9), seed=st.integers(0, 2**16), masked=st.booleans())
def test_fast_forward_equals_the_literal_definition(k: int, b: int, seed: int, masked: bool) -> None:
    """``forward`` (no per-factor W_2, folded score map) is the paper's FAB: same v, α and gradients."""
    fab = _fab(seed % 7).double()
    x, obs, ids, meta = (t.double() for t in _inputs(b, k, seed))
    x.requires_grad_(True)
    mask = torch.rand(b, k, generator=torch.Generator().manual_seed(seed)) > 0.3 if masked else None
    v, alpha = fab(x, obs, ids, meta, mask)
    v_ref, alpha_ref, _ = fab.reference(x, obs, ids, meta, mask)
    torch.testing.assert_close(v, v_ref, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(alpha, alpha_ref, rtol=1e-9, atol=1e-10)
    w = torch.randn(v.shape, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    params = [x, *fab.parameters()]
    grads = torch.autograd.grad((v * w).sum(), params, allow_unused=True)
    grads_ref = torch.autograd.grad((v_ref * w).sum(), params, allow_unused=True)
    for g, g_ref in zip(grads, grads_ref, strict=True):
        if g is None or g_ref is None:
            assert (g is None or not g.any()) and (g_ref is None or not g_ref.any())
        else:
            torch.testing.assert_close(g, g_ref, rtol=1e-8, atol=1e-10)


@settings(max_examples=25, deadline=None)
@given(k=st.integers(0, 12), b=st.integers(1, 9), seed=st.integers(0, 2**16), unit=st.floats(0.5, 100.0),
       clip=st.floats(0.5, 10.0))
def test_frozen_potential_equals_the_modules(k: int, b: int, seed: int, unit: float, clip: float) -> None:
    """The shaping path's Φ (W_2 folded into the VPM, normalisation as a multiply-add, σ_R folded into
    the output) is ``unit · vpm(fab(x, o))`` of the clipped, normalised inputs for any number of factors."""
    fab = _fab(seed % 7).double()
    vpm = ValuePotential(16, hidden=16).double()
    f, obs, ids, meta = (t.double() * 3.0 if i < 2 else t.double() for i, t in enumerate(_inputs(b, k, seed)))
    gen = torch.Generator().manual_seed(seed + 2)
    f_shift, o_shift = torch.randn(k, generator=gen, dtype=torch.float64), torch.randn(OBS, generator=gen,
                                                                                          dtype=torch.float64)
    f_inv, o_inv = (torch.rand(n, generator=gen, dtype=torch.float64) + 0.5 for n in (k, OBS))
    x, o = (f * f_inv + f_shift).clamp(-clip, clip), (obs * o_inv + o_shift).clamp(-clip, clip)
    expected = vpm(fab(x, o, ids, meta)[0]) * unit
    frozen = FrozenPotential(fab, vpm, ids, meta, f_shift=f_shift, f_inv=f_inv, o_shift=o_shift, o_inv=o_inv,
                             clip=clip, unit=unit)
    torch.testing.assert_close(frozen(f, obs), expected, rtol=1e-9, atol=1e-9)


def test_single_factor_gets_all_attention() -> None:
    fab = _fab()
    x, obs, ids, meta = _inputs(4, 1)
    v, alpha = fab(x, obs, ids, meta)
    z = fab.embed(x, ids, meta)
    assert torch.equal(alpha, torch.ones(4, 1))
    torch.testing.assert_close(v, z[:, 0])
    torch.testing.assert_close(attention_entropy(alpha), torch.zeros(4))


def test_masking_a_factor_equals_dropping_it() -> None:
    fab = _fab()
    x, obs, ids, meta = _inputs(6, 12)
    keep = torch.tensor([0, 2, 3, 5, 6, 7, 9, 11])
    mask = torch.zeros(12, dtype=torch.bool)
    mask[keep] = True
    v_m, a_m = fab(x, obs, ids, meta, mask)
    v_d, a_d = fab(x[:, keep], obs, ids[keep], meta[keep])
    torch.testing.assert_close(v_m, v_d, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(a_m[:, keep], a_d, rtol=1e-5, atol=1e-6)
    assert torch.all(a_m[:, ~mask] == 0)

    # per-row masks: each row drops a different set, still equal to dropping per row
    row_mask = torch.rand(6, 12, generator=torch.Generator().manual_seed(3)) > 0.5
    row_mask[:, 0] = True
    row_mask[5] = False  # a row with nothing present: no attention, v = 0, no NaN
    v_r, a_r = fab(x, obs, ids, meta, row_mask)
    for i in range(5):
        cols = row_mask[i].nonzero().squeeze(1)
        v_i, _ = fab(x[i : i + 1, cols], obs[i : i + 1], ids[cols], meta[cols])
        torch.testing.assert_close(v_r[i : i + 1], v_i, rtol=1e-5, atol=1e-6)
    assert torch.all(a_r[5] == 0) and torch.all(v_r[5] == 0)
    assert torch.isfinite(v_r).all()


def test_masked_factor_values_do_not_matter_and_gradients_stay_finite() -> None:
    fab = _fab()
    x, obs, ids, meta = _inputs(5, 4)
    mask = torch.tensor([True, False, True, True])
    x2 = x.clone()
    x2[:, 1] = 1e6
    v1, _ = fab(x, obs, ids, meta, mask)
    v2, _ = fab(x2, obs, ids, meta, mask)
    torch.testing.assert_close(v1, v2)
    none = torch.zeros(4, dtype=torch.bool)
    v0, _ = fab(x, obs, ids, meta, none)
    v0.sum().backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in fab.parameters())


def test_zero_factors_give_zero_aggregation() -> None:
    fab = _fab()
    v, alpha = fab(torch.zeros(3, 0), torch.randn(3, OBS), torch.zeros(0, 8), torch.zeros(0, META_DIM))
    assert v.shape == (3, 16) and alpha.shape == (3, 0) and torch.all(v == 0)


def test_tce_ignores_padding_before_the_episode_start() -> None:
    torch.manual_seed(0)
    tce = TemporalContextEncoder(8, hidden=16)
    ctx = torch.randn(3, 7, 8)
    valid = torch.zeros(3, 7, dtype=torch.bool)
    valid[0, :] = True
    valid[1, 4:] = True  # three steps of history
    # row 2: no history at all
    out = tce(ctx, valid)
    noisy = ctx.clone()
    noisy[1, :4] = 1e3
    noisy[2] = -1e3
    torch.testing.assert_close(tce(noisy, valid), out)
    short = tce(ctx[1:2, 4:], torch.ones(1, 3, dtype=torch.bool))
    torch.testing.assert_close(out[1:2], short)


def test_fresh_potential_does_not_depend_on_factor_order() -> None:
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(32, 6)).astype(np.float32)
    a, buf_a = make_hars(toy_factors(["f_a", "f_b", "f_c"]), seed=3)
    b, buf_b = make_hars(toy_factors(["f_c", "f_a", "f_b"]), seed=3)
    for src, buf in ((a, buf_a), (b, buf_b)):
        fill_episodes(src, buf, [20], np.random.default_rng(1))
    torch.testing.assert_close(a.potential(obs), b.potential(obs), rtol=1e-5, atol=1e-6)
    att_a, att_b = a.attention(obs), b.attention(obs)
    assert att_a.keys() == att_b.keys()
    for name in att_a:
        assert att_a[name] == pytest.approx(att_b[name], abs=1e-6)


def test_id_embedding_follows_the_name_after_training() -> None:
    rng = np.random.default_rng(0)
    src, buf = make_hars(toy_factors(["f_a", "f_b", "f_c"]))
    fill_episodes(src, buf, [30, 30], rng)
    for step in range(5):
        batch = buf.sample(16, rng)
        src.relabel(batch)
        src.update(batch, step)
    obs = rng.normal(size=(20, 6)).astype(np.float32)
    reordered = toy_factors(["f_b", "f_c", "f_a"])
    torch.testing.assert_close(src.proxy_potential(reordered, obs), src.potential(obs), rtol=1e-5, atol=1e-5)
    # the slots are a name table: a new name gets a fresh slot, old names keep theirs
    slots = dict(src.nets.slots)
    src.set_program(toy_factors(["f_c", "f_new", "f_a"]))
    assert {n: src.nets.slots[n] for n in slots} == slots
    assert src.nets.slots["f_new"] == len(slots)
