"""In-process evaluation of admitted programs: shapes, values, and distrust of outputs."""

from __future__ import annotations

import numpy as np
import pytest

from mira.factors import (
    CompiledProgram,
    Factor,
    FactorProgram,
    FactorRuntimeError,
    InadmissibleCodeError,
    example_program,
)
from mira.factors.whitelist import NP_PROXY
from mira.tasks import load_task


@pytest.fixture(scope="module")
def cheetah() -> tuple[object, np.ndarray, np.ndarray]:
    card = load_task("halfcheetah", check_env=False)
    card.bind(17)
    rng = np.random.default_rng(3)
    return card, rng.normal(size=(300, 17)), rng.uniform(-1, 1, size=(300, 6))


def program_of(*factors: tuple[str, str, str]) -> FactorProgram:
    return FactorProgram("halfcheetah", 0, tuple(Factor(n, k, c, "d", "u", "[-1, 1]") for n, k, c in factors))


def test_example_program_values(cheetah: tuple[object, np.ndarray, np.ndarray]) -> None:
    card, obs, acts = cheetah
    compiled = CompiledProgram(example_program("halfcheetah", 1), card)  # type: ignore[arg-type]
    view = card.state_view(obs)  # type: ignore[attr-defined]
    phi, aux = compiled.phi(view), compiled.aux(view, acts)
    assert compiled.phi_names == ["r_vel", "r_upright", "r_stable"] and compiled.aux_names == ["r_ctrl"]
    assert phi.shape == (300, 3) and aux.shape == (300, 1) and phi.dtype == np.float64
    pitch, vx, rate = obs[:, 1], obs[:, 8], obs[:, 10]
    np.testing.assert_allclose(phi[:, 0], vx * (1 - np.tanh(2 * pitch**2)))
    np.testing.assert_allclose(phi[:, 1], -(pitch**2))
    np.testing.assert_allclose(phi[:, 2], -0.05 * rate**2)
    np.testing.assert_allclose(aux[:, 0], -0.1 * np.sum(acts**2, axis=1))
    one = compiled.phi(card.state_view(obs[0]))  # type: ignore[attr-defined]
    np.testing.assert_allclose(one[0], phi[0])
    assert set(compiled.evaluate(view, acts)) == {"r_vel", "r_upright", "r_stable", "r_ctrl"}
    assert all(h.errors == 0 and h.nonfinite_values == 0 for h in compiled.health.values())


def test_bad_values_become_counted_zeros(cheetah: tuple[object, np.ndarray, np.ndarray]) -> None:
    card, obs, _ = cheetah
    program = program_of(
        ("ok", "PHI", "def ok(s):\n    return s.x_velocity\n"),
        ("nan", "PHI", "def nan(s):\n    return np.arccosh(s.x_velocity + 1.0)\n"),  # NaN for negative velocities
        ("inf", "PHI", "def inf(s):\n    return s.x_velocity / 0.0\n"),
        ("shape", "PHI", "def shape(s):\n    return s.obs\n"),
        ("scalar", "PHI", "def scalar(s):\n    return 1.0\n"),
        ("boom", "PHI", "def boom(s):\n    return s.obs[:, 99]\n"),
    )
    compiled = CompiledProgram(program, card)  # type: ignore[arg-type]
    out = compiled.phi(card.state_view(obs))  # type: ignore[attr-defined]
    assert out.shape == (300, 6) and np.all(np.isfinite(out))
    np.testing.assert_allclose(out[:, 0], obs[:, 8])
    negative = int(np.sum(obs[:, 8] < 0))
    assert compiled.health["nan"].nonfinite_values == negative and np.all(out[obs[:, 8] < 0, 1] == 0)
    assert compiled.health["inf"].nonfinite_values == 300
    assert compiled.health["shape"].bad_shape == 1 and np.all(out[:, 3] == 0)
    assert compiled.health["scalar"].bad_shape == 1
    assert compiled.health["boom"].errors == 1 and "IndexError" in compiled.health["boom"].last_error
    strict = CompiledProgram(program, card, strict=True)  # type: ignore[arg-type]
    with pytest.raises(FactorRuntimeError):
        strict.phi(card.state_view(obs))  # type: ignore[attr-defined]


def test_only_admitted_code_is_compiled(cheetah: tuple[object, np.ndarray, np.ndarray]) -> None:
    card, _, _ = cheetah
    for code in [
        "def f(s):\n    return open('x')\n",
        "def f(s):\n    return s.next_pitch\n",
        "def f(s):\n    return ().__class__\n",
    ]:
        with pytest.raises(InadmissibleCodeError) as info:
            CompiledProgram(program_of(("f", "PHI", code)), card)  # type: ignore[arg-type]
        assert info.value.violations and info.value.violations[0].factor == "f"


def test_restricted_namespace(cheetah: tuple[object, np.ndarray, np.ndarray]) -> None:
    card, obs, _ = cheetah
    compiled = CompiledProgram(example_program("halfcheetah", 0), card)  # type: ignore[arg-type]
    fn = compiled._phi[0][1]
    assert fn.__globals__["__builtins__"] == {}
    assert set(fn.__globals__) - {"__builtins__", "np", "math", "range", "abs", "min", "max", "float"} <= {
        "r_vel",
        *(k for k in fn.__globals__ if k.startswith("_k")),
    }
    with pytest.raises(AttributeError):
        NP_PROXY.sum = print  # type: ignore[attr-defined]
    assert not hasattr(NP_PROXY, "load") and not hasattr(NP_PROXY, "lib")
    view = card.state_view(obs)  # type: ignore[attr-defined]
    with pytest.raises(ValueError):
        view.obs[0, 0] = 1.0


def test_actions_must_match_the_batch(cheetah: tuple[object, np.ndarray, np.ndarray]) -> None:
    card, obs, acts = cheetah
    compiled = CompiledProgram(example_program("halfcheetah", 0), card)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        compiled.aux(card.state_view(obs), acts[:10])  # type: ignore[attr-defined]
