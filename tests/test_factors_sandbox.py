"""Sandbox realizability on real states, and a worker that survives hostile code with the parent intact."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from mira.factors import (
    Factor,
    FactorProgram,
    SandboxLimits,
    collect_states,
    example_program,
    sandbox_check,
)
from mira.tasks import load_task


def program_of(task: str, **codes: str) -> FactorProgram:
    return FactorProgram(task, 0, tuple(Factor(n, "PHI", c, "d", "u", "[-20, 20]") for n, c in codes.items()))


@pytest.mark.parametrize("task", ["halfcheetah", "humanoidstandup"])
def test_example_programs_pass_on_real_states(task: str) -> None:
    card = load_task(task)
    for version in (0, 1):
        report = sandbox_check(example_program(task, version), card)
        assert report.ok, report.lines()
        assert report.batch_size == 512 and task != "" and card.env_id in report.state_source
        assert report.wall_seconds < 15
        for verdict in report.factors.values():
            figures = verdict.figures
            assert verdict.passed and figures["shape"] == [512] and figures["nonfinite_ratio"] == 0.0
            for key in (
                "mean",
                "std",
                "min",
                "max",
                "excess_kurtosis",
                "saturation_ratio",
                "lipschitz_q",
                "batch_coupling",
            ):
                assert np.isfinite(figures[key]), key
        json.dumps(report.to_dict())  # every figure is loggable
    if task == "humanoidstandup":
        assert report.factors["r_survival"].figures["constant"] is True


def test_realizability_failures_are_reported_with_figures() -> None:
    card = load_task("halfcheetah")
    program = program_of(
        "halfcheetah",
        ok="def ok(s):\n    return s.x_velocity\n",
        nan="def nan(s):\n    return np.arccosh(s.x_velocity + 1.0)\n",  # NaN below 0 (no static rule sees it)
        inf="def inf(s):\n    return s.obs[:, 8] * 1e308 * 10.0\n",
        shape="def shape(s):\n    return s.obs\n",
        scalar="def scalar(s):\n    return 0.5\n",
        coupled="def coupled(s):\n    return s.x_velocity - np.mean(s.x_velocity)\n",
        steep="def steep(s):\n    return 1e6 * s.pitch\n",
        clipped="def clipped(s):\n    return np.clip(s.x_velocity, -0.05, 0.05)\n",
        heavy="def heavy(s):\n    return np.exp(8.0 * np.abs(s.x_velocity))\n",
        raises="def raises(s):\n    return s.obs[:, 99]\n",
    )
    report = sandbox_check(program, card)
    assert not report.ok and report.isolation
    expected = {
        "nan": "non-finite",
        "inf": "non-finite",
        "shape": "shape",
        "scalar": "shape",
        "coupled": "batch-coupling",
        "steep": "lipschitz",
        "clipped": "saturation",
        "heavy": "kurtosis",
        "raises": "sandbox-error",
    }
    assert report.factors["ok"].passed
    for name, rule in expected.items():
        verdict = report.factors[name]
        assert not verdict.passed and rule in {r.rule for r in verdict.reasons}, (name, verdict.reasons)
    assert report.factors["steep"].figures["lipschitz_q"] > 1e5
    assert report.factors["clipped"].figures["saturation_ratio"] > 0.3
    assert report.factors["heavy"].figures["excess_kurtosis"] > 50
    assert report.factors["coupled"].figures["batch_coupling"] > 1e-3
    lines = report.lines()
    assert any(line.startswith("nan:0: [non-finite]") for line in lines)


def test_static_errors_are_not_run(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    program = program_of(
        "halfcheetah",
        ok="def ok(s):\n    return s.pitch\n",
        bad=f"def bad(s):\n    open('{marker}', 'w')\n    return s.pitch\n",
    )
    report = sandbox_check(program, load_task("halfcheetah"))
    assert report.factors["ok"].passed and not report.factors["bad"].passed
    assert "builtin" in {v.rule for v in report.factors["bad"].reasons}
    assert "shape" not in report.factors["bad"].figures  # never ran
    assert not marker.exists()


def test_states_from_a_replay_buffer() -> None:
    card = load_task("halfcheetah")
    obs, acts = collect_states(card, 512, seed=0)
    report = sandbox_check(example_program("halfcheetah", 0), card, states=obs[:100], actions=acts[:100])
    assert report.ok and report.batch_size == 100 and "given" in report.state_source
    with pytest.raises(ValueError):
        sandbox_check(example_program("halfcheetah", 0), card, states=obs[:100])


@pytest.mark.slow
def test_worker_survives_hostile_code_that_skipped_the_checker(tmp_path: Path) -> None:
    """The OS-level layer on its own: unchecked code burns CPU, hogs memory, escapes to os, dies."""
    marker = tmp_path / "marker"
    walk = (
        "    for c in ().__class__.__base__.__subclasses__():\n"
        "        if c.__name__ == '_wrap_close':\n"
        "            g = c.__init__.__globals__\n"
    )
    codes = {
        "burn": "def burn(s):\n    while True:\n        pass\n",
        "hog": "def hog(s):\n    x = [0.0]\n    while True:\n        x = x + x\n",
        "writer": (
            "def writer(s):\n"
            + walk
            + f"            g['system']('touch {marker}')\n"
            + f"            g['__builtins__']['open']('{marker}', 'w').write('x')\n"
            + "    return s.x_velocity\n"
        ),
        "mkdir": "def mkdir(s):\n" + walk + f"            g['mkdir']('{marker}')\n    return s.x_velocity\n",
        "killer": "def killer(s):\n" + walk + "            g['abort']()\n    return s.x_velocity\n",
        "ok": "def ok(s):\n    return s.x_velocity\n",
    }
    program = program_of("halfcheetah", **codes)
    limits = SandboxLimits(per_factor_timeout_s=1.5, wall_timeout_s=14.0, memory_mb=256)
    started = time.monotonic()
    report = sandbox_check(program, load_task("halfcheetah"), static_check=False, limits=limits)
    elapsed = time.monotonic() - started
    assert elapsed < 15.0
    rules = {name: {r.rule for r in v.reasons} for name, v in report.factors.items()}
    assert rules["burn"] == {"sandbox-timeout"}
    assert rules["hog"] & {"sandbox-memory", "sandbox-timeout"}
    assert rules["writer"] and rules["mkdir"]
    assert rules["killer"] == {"sandbox-crash"}
    assert report.factors["ok"].passed  # the restarted worker still judged the rest
    assert report.worker_starts >= 3
    assert not marker.exists()


def test_whole_check_is_bounded_in_time() -> None:
    burners = {f"b{i}": f"def b{i}(s):\n    while True:\n        pass\n" for i in range(4)}
    limits = SandboxLimits(per_factor_timeout_s=1.0, wall_timeout_s=3.0)
    started = time.monotonic()
    report = sandbox_check(
        program_of("halfcheetah", **burners), load_task("halfcheetah"), static_check=False, limits=limits
    )
    assert time.monotonic() - started < 6.0
    assert not report.ok and all(not v.passed for v in report.factors.values())
    assert all({r.rule for r in v.reasons} == {"sandbox-timeout"} for v in report.factors.values())


def _hopper_program(code: str) -> FactorProgram:
    return FactorProgram.from_json({"task": "hopper", "version": 0, "factors": [
        {"name": "r_x", "type": "PHI", "code": code, "doc": "d", "units": "1", "range_hint": "[-10, 10]"}]})


def test_a_division_by_a_margin_that_reaches_zero_where_the_task_ends_is_refused() -> None:
    """Random rollouts never bring Hopper's torso down to where its episode ends, so the factor is finite
    on every sandbox state; the card declares the margin's range, and the division is refused there."""
    card = load_task("hopper")
    report = sandbox_check(_hopper_program("def r_x(s):\n    v = s.x_velocity\n    return v / s.height_margin\n"),
                           card)
    assert not report.ok
    (violation,) = [v for v in report.factors["r_x"].reasons if v.rule == "singular"]
    assert violation.line == 3
    assert "division by s.height_margin, which is 0 where height_margin = 0" in violation.message
    # Shifted away from zero on these states, the same shape is still refused: nothing in the code keeps the
    # argument away from 0 where a trained policy goes (rule unguarded); with its guard written, it passes.
    shifted = sandbox_check(_hopper_program("def r_x(s):\n    return s.x_velocity / (s.height_margin + 2.0)\n"),
                            card)
    assert not shifted.ok and any(v.rule == "unguarded" for v in shifted.violations)
    guarded = "def r_x(s):\n    return s.x_velocity / (np.maximum(s.height_margin, 0.0) + 2.0)\n"
    assert sandbox_check(_hopper_program(guarded), card).ok
    assert sandbox_check(_hopper_program("def r_x(s):\n    return np.log(1.0 + np.abs(s.x_velocity))\n"), card).ok
    logged = sandbox_check(_hopper_program("def r_x(s):\n    return np.log(s.x_velocity + 1.0)\n"), card)
    assert any(v.rule in ("singular", "unguarded") and "np.log of" in v.message for v in logged.violations)


def test_a_potential_flat_outside_its_band_is_a_shape_factor_not_a_saturated_feature() -> None:
    """The same clipped code is refused as a PHI feature (the head would fit a flat column) and admitted,
    with a warning, as a SHAPE potential, which is meant to ramp at one band and stay flat elsewhere."""
    code = "def ramp(s):\n    return np.clip(s.x_velocity, -0.05, 0.05)\n"
    card = load_task("halfcheetah")
    program = program_of("halfcheetah", ramp=code)
    as_phi = sandbox_check(program, card).factors["ramp"]
    shape = Factor("ramp", "SHAPE", code, doc="a ramp", units="1", range_hint="[-0.05, 0.05]")
    as_shape = sandbox_check(program.with_factors([shape]), card).factors["ramp"]
    assert not as_phi.passed and {r.rule for r in as_phi.reasons} == {"saturation"}
    assert as_shape.passed and as_shape.figures["saturation_ratio"] > 0.3
    assert any("flat outside" in w for w in as_shape.warnings)
