"""Sandbox realizability (section 4.4.4, second stage): run admissible code on real states, elsewhere.

Passing the static whitelist is necessary, not sufficient: a factor can still divide by zero, be
all-saturated, be absurdly steep, or couple the states of a batch. So before a program is used,
its factors run in a *separate worker process* (``python -I``, see :mod:`mira.factors._worker`)
under limits it cannot lift, on a held-out batch of real states of the task's environment, and
the parent computes every figure from the raw outputs:

* ``shape``: the output is a numeric array ``[B]``;
* ``non-finite``: no NaN/Inf, on the batch and on its perturbations;
* ``kurtosis``: excess kurtosis of the outputs at most ``max_excess_kurtosis`` (heavy tails make
  attention and the potential unstable);
* ``saturation``: fraction of outputs piled up at the batch minimum or maximum (within 1e-6 of the
  range, i.e. clipped or hard-saturated; an extreme counts only when it holds at least 1 % of the
  batch) at most ``max_saturation``; for a SHAPE factor only a warning: a potential that ramps up at
  one band of states is meant to be flat elsewhere, and a fixed potential feeds neither the
  decomposition head nor the attention that flat features destabilise;
* ``lipschitz``: the ``lipschitz_quantile`` quantile over states of the gradient norm with respect
  to the observation, estimated by randomized finite differences (Gaussian directions ``u``, so
  ``E[(∇f·u)^2] = |∇f|^2``), at most ``max_lipschitz``; for a SHAPE factor, whose size is its author's
  choice (a potential sized in steps of the task's reward), the gradient per unit of its declared range
  (a SHAPE factor without a finite declared range is judged in absolute units);
* ``batch-coupling``: evaluating on the first half of the batch, or on the first state alone,
  gives the same values as on the whole batch (a factor is a function of one state, so
  ``x - np.mean(x)`` is refused).

The worker's limits: ``RLIMIT_CPU``, ``RLIMIT_AS``, ``RLIMIT_FSIZE = 0``, ``RLIMIT_NOFILE = 0`` and
``RLIMIT_NPROC = 0`` once set up, an empty temporary working directory (a ``chroot`` into it and a
switch to user ``nobody`` when running as root), a private network namespace where the kernel
allows one, inherited descriptors closed, and a wall-clock deadline per factor and per check
enforced by the parent, which kills the worker's whole process group. Which layers were in force
is recorded in :attr:`SandboxReport.isolation`. The parent survives anything the worker does: a
hang or a CPU burn (killed at the deadline), a memory blow-up (``MemoryError`` under
``RLIMIT_AS``), a crash (reported with the signal), garbage on the pipe (validated, never
unpickled). A worker that dies on one factor is restarted for the remaining ones while time is
left, so every factor gets its own verdict. The whole check stays within ``wall_timeout_s``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mira.factors.checker import check_code, check_metadata, parse_range_hint
from mira.factors.program import FactorProgram
from mira.factors.sandbox_process import SandboxLimits, WorkerRun, decode_output, run_workers
from mira.factors.singular import singular_operations
from mira.factors.violations import Violation

if TYPE_CHECKING:
    from mira.tasks.card import TaskCard


@dataclass(frozen=True)
class SandboxThresholds:
    """Acceptance bounds of the realizability checks."""

    max_excess_kurtosis: float = 50.0
    max_saturation: float = 0.3
    max_lipschitz: float = 1000.0
    lipschitz_quantile: float = 0.9
    fd_directions: int = 8
    fd_step: float = 1e-5
    coupling_tolerance: float = 1e-7  # relative to 1 + |value|
    range_tolerance: float = 0.05  # fraction outside range_hint that earns a warning


@dataclass
class FactorVerdict:
    """One factor's sandbox outcome: figures, verdict, and the reasons for it."""

    name: str
    type: str
    passed: bool
    reasons: list[Violation] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "type": self.type,
            "passed": self.passed,
            "reasons": [v.to_dict() for v in self.reasons],
            "warnings": list(self.warnings),
            "figures": dict(self.figures),
        }


@dataclass
class SandboxReport:
    """Every figure and verdict of one sandbox check (logged with each SRR candidate)."""

    ok: bool
    factors: dict[str, FactorVerdict]
    batch_size: int
    state_source: str
    isolation: list[str]
    wall_seconds: float
    worker_starts: int
    limits: SandboxLimits
    thresholds: SandboxThresholds

    @property
    def violations(self) -> list[Violation]:
        return [v for verdict in self.factors.values() for v in verdict.reasons]

    def lines(self) -> list[str]:
        return [str(v) for v in self.violations]

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "batch_size": self.batch_size,
            "state_source": self.state_source,
            "isolation": list(self.isolation),
            "wall_seconds": self.wall_seconds,
            "worker_starts": self.worker_starts,
            "limits": asdict(self.limits),
            "thresholds": asdict(self.thresholds),
            "factors": {name: v.to_dict() for name, v in self.factors.items()},
        }


# --------------------------------------------------------------------------- states

_STATE_CACHE: dict[tuple[str, str, int, int], tuple[np.ndarray, np.ndarray]] = {}


def collect_states(card: TaskCard, n_states: int = 512, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n_states`` real observations and actions in [-1, 1] from a uniformly random policy.

    Episodes are cut at 256 steps so the batch mixes early and later states. Cached per process:
    the batch is fixed for a given card, size and seed, so candidates are compared on equal terms.
    """
    key = (card.env_id, json.dumps(card.env_kwargs, sort_keys=True, default=str), n_states, seed)
    cached = _STATE_CACHE.get(key)
    if cached is None:
        from mira.tasks.envs import make_env

        env = make_env(card, seed=seed, max_episode_steps=256)
        rng = np.random.default_rng(seed)
        act_dim = int(env.action_space.shape[0])  # type: ignore[index]
        obs_rows: list[np.ndarray] = []
        act_rows: list[np.ndarray] = []
        obs, _ = env.reset(seed=seed)
        episode = 0
        while len(obs_rows) < n_states:
            action = rng.uniform(-1.0, 1.0, size=act_dim)
            obs_rows.append(np.asarray(obs, dtype=np.float64))
            act_rows.append(action)
            obs, _, terminated, truncated, _ = env.step(action.astype(np.float32))
            if terminated or truncated:
                episode += 1
                obs, _ = env.reset(seed=seed + episode)
        env.close()
        cached = (np.stack(obs_rows), np.stack(act_rows))
        for arr in cached:
            arr.setflags(write=False)
        _STATE_CACHE[key] = cached
    return cached


# --------------------------------------------------------------------------- figures


def _kurtosis(values: np.ndarray) -> float:
    centred = values - values.mean()
    var = float(np.mean(centred**2))
    if var <= 0.0:
        return 0.0
    return float(np.mean(centred**4) / var**2 - 3.0)


def _saturation(values: np.ndarray) -> float:
    lo, hi = float(values.min()), float(values.max())
    span = hi - lo
    if span <= 1e-12 * (1.0 + abs(hi)):
        return 0.0
    tol = 1e-6 * span
    at_lo = int(np.count_nonzero(values <= lo + tol))
    at_hi = int(np.count_nonzero(values >= hi - tol))
    floor = max(2, int(0.01 * values.size))
    piled = (at_lo if at_lo >= floor else 0) + (at_hi if at_hi >= floor else 0)
    return piled / values.size


def _figures_and_reasons(
    name: str,
    hint: str,
    record: dict[str, Any],
    batch: int,
    half: int,
    deltas: Sequence[float],
    th: SandboxThresholds,
    kind: str = "PHI",
) -> tuple[dict[str, Any], list[Violation], list[str]]:
    figures: dict[str, Any] = {
        "seconds": record.get("seconds") if isinstance(record.get("seconds"), float) else None
    }
    reasons: list[Violation] = []
    warnings: list[str] = []

    def fail(rule: str, message: str) -> None:
        reasons.append(Violation(name, rule, 0, message))

    status = record.get("status")
    error = str(record.get("error", ""))[:500]
    if status != "ok":
        rule = {
            "timeout": "sandbox-timeout",
            "not-run": "sandbox-timeout",
            "memory": "sandbox-memory",
            "crash": "sandbox-crash",
        }.get(str(status), "sandbox-error")
        fail(rule, error or str(status))
        return figures, reasons, warnings
    outputs = record.get("outputs")
    if not isinstance(outputs, dict):
        fail("sandbox-crash", "the worker sent no outputs")
        return figures, reasons, warnings
    decoded = {label: decode_output(rec) for label, rec in outputs.items() if isinstance(label, str)}
    base = decoded.get("base")
    if base is None:
        fail("sandbox-crash", "the worker sent a malformed output")
        return figures, reasons, warnings
    shape, values = base
    figures["shape"] = list(shape)
    if shape != (batch,) or values is None:
        dtype = outputs["base"].get("dtype") if isinstance(outputs["base"], dict) else "?"
        fail("shape", f"returned shape {list(shape)} (dtype {dtype}); expected [{batch}] floats")
        return figures, reasons, warnings
    finite = np.isfinite(values)
    figures["nonfinite_ratio"] = float(1.0 - finite.mean())
    if not finite.all():
        fail("non-finite", f"{int((~finite).sum())} of {batch} outputs are NaN/Inf")
        return figures, reasons, warnings
    lo, hi = float(values.min()), float(values.max())
    figures.update(
        mean=float(values.mean()),
        std=float(values.std()),
        min=lo,
        max=hi,
        p01=float(np.quantile(values, 0.01)),
        p99=float(np.quantile(values, 0.99)),
    )
    constant = hi - lo <= 1e-12 * (1.0 + abs(hi))
    figures["constant"] = bool(constant)
    if constant:
        warnings.append("constant on the sandbox batch: it carries no information about the state")
    figures["excess_kurtosis"] = _kurtosis(values)
    if not constant and figures["excess_kurtosis"] > th.max_excess_kurtosis:
        fail("kurtosis", f"excess kurtosis {figures['excess_kurtosis']:.1f} > {th.max_excess_kurtosis:g}")
    figures["saturation_ratio"] = _saturation(values)
    if figures["saturation_ratio"] > th.max_saturation:
        message = f"{figures['saturation_ratio']:.0%} of outputs sit at an extreme (> {th.max_saturation:.0%})"
        if kind == "SHAPE":
            warnings.append(f"{message}: flat outside the states where the potential ramps")
        else:
            fail("saturation", message)
    bounds = parse_range_hint(hint)
    if bounds is not None:
        outside = float(np.mean((values < bounds[0]) | (values > bounds[1])))
        figures["outside_range_hint"] = outside
        if outside > th.range_tolerance:
            warnings.append(f"{outside:.0%} of outputs fall outside range_hint {hint}")
    # batch independence
    coupling = 0.0
    for label, size in (("half", half), ("single", 1)):
        sub = decoded.get(label)
        if sub is None or sub[1] is None or sub[0] != (size,):
            fail(
                "batch-coupling",
                f"on a batch of {size} state(s) it returned shape "
                f"{list(sub[0]) if sub else '?'}; the value of a state must not depend on the batch",
            )
            break
        dev = np.abs(sub[1] - values[:size]) / (1.0 + np.abs(values[:size]))
        coupling = max(coupling, float(np.max(dev, initial=0.0)) if np.all(np.isfinite(dev)) else math.inf)
    figures["batch_coupling"] = coupling
    if coupling > th.coupling_tolerance and not any(r.rule == "batch-coupling" for r in reasons):
        fail("batch-coupling", f"values change by up to {coupling:.3g} (relative) when the batch changes")
    # Lipschitz estimate
    squares = []
    for k, delta in enumerate(deltas):
        pert = decoded.get(f"dir{k}")
        if pert is None or pert[1] is None or pert[0] != (batch,):
            fail("shape", "returned a different shape on perturbed states")
            break
        if not np.all(np.isfinite(pert[1])):
            fail("non-finite", "NaN/Inf on slightly perturbed states")
            break
        squares.append(((pert[1] - values) / delta) ** 2)
    if len(squares) == len(deltas) and squares:
        grad = np.sqrt(np.mean(np.stack(squares), axis=0))
        unit = ""
        if kind == "SHAPE" and bounds is not None and np.isfinite(bounds[1] - bounds[0]) and bounds[1] > bounds[0]:
            grad = grad / (bounds[1] - bounds[0])
            unit = " per unit of its declared range"
        figures["lipschitz_q"] = float(np.quantile(grad, th.lipschitz_quantile))
        figures["lipschitz_max"] = float(grad.max())
        if figures["lipschitz_q"] > th.max_lipschitz:
            fail(
                "lipschitz",
                f"gradient-norm q{th.lipschitz_quantile:g} = {figures['lipschitz_q']:.3g}{unit} > "
                f"{th.max_lipschitz:g}",
            )
    return figures, reasons, warnings


# --------------------------------------------------------------------------- public API


def sandbox_check(
    program: FactorProgram,
    card: TaskCard,
    *,
    states: np.ndarray | None = None,
    actions: np.ndarray | None = None,
    n_states: int = 512,
    seed: int = 0,
    limits: SandboxLimits | None = None,
    thresholds: SandboxThresholds | None = None,
    static_check: bool = True,
) -> SandboxReport:
    """Run every factor of ``program`` in the sandbox on real states and report figures and verdicts.

    ``states`` (``[B, obs_dim]``, e.g. from a replay buffer) and ``actions`` (``[B, act_dim]`` in
    [-1, 1]) replace the default batch of ``n_states`` states from a random policy in the task's
    environment. Factors with static errors are not run (their static violations are their
    verdict). ``static_check=False`` is for the test suite only: it sends unchecked code to the
    worker to show that the OS-level limits hold on their own.
    """
    limits = limits or SandboxLimits()
    th = thresholds or SandboxThresholds()
    started = time.monotonic()
    deadline = started + limits.wall_timeout_s
    if states is None:
        states, default_actions = collect_states(card, n_states, seed)
        source = f"{card.env_id}: {len(states)} states of a uniformly random policy (seed {seed})"
        if actions is None:
            actions = default_actions
    else:
        source = f"{len(states)} states given by the caller"
    obs = np.array(states, dtype=np.float64, ndmin=2)
    batch = int(obs.shape[0])
    if batch < 4:
        raise ValueError("the sandbox needs a batch of at least 4 states")
    if actions is None:
        raise ValueError("actions are needed with caller-given states (AUX factors read them)")
    acts = np.array(actions, dtype=np.float64, ndmin=2)
    if acts.shape[0] != batch:
        raise ValueError(f"{acts.shape[0]} actions for {batch} states")
    try:
        bound: int | None = card.obs_dim
    except RuntimeError:
        bound = None
    if bound != obs.shape[1]:
        card.bind(int(obs.shape[1]))
    features = list(card.feature_names)

    rng = np.random.default_rng(seed + 7919)
    deltas = [th.fd_step] * th.fd_directions
    batches = [_batch_values(card, obs)]
    for delta in deltas:
        batches.append(_batch_values(card, obs + delta * rng.standard_normal(obs.shape)))

    declared = {f.name: f.range for f in card.features if f.range is not None}
    verdicts: dict[str, FactorVerdict] = {}
    runnable: list[dict[str, str]] = []
    for f in program.factors:
        static = check_code(f.name, f.type, f.code, features) if static_check else []
        meta = check_metadata(f)
        errors = [v for v in static + meta if v.is_error]
        errors += singular_operations(f.name, f.code, batches[0], declared)
        verdicts[f.name] = FactorVerdict(
            f.name, f.type, passed=False, reasons=errors, warnings=[str(v) for v in meta if not v.is_error]
        )
        if not [v for v in static if v.is_error]:
            runnable.append({"name": f.name, "type": f.type, "code": f.code})

    job = {
        "features": features,
        "batches": batches,
        "actions": acts,
        "batch": batch,
        "half": batch // 2,
        "unchecked": not static_check,
        "limits": {"cpu_s": limits.cpu_s, "mem_bytes": limits.memory_mb * 1024 * 1024},
    }
    run = run_workers(runnable, job, limits, deadline) if runnable else WorkerRun()
    for spec in runnable:
        verdict = verdicts[spec["name"]]
        hint = program.factor(spec["name"]).range_hint
        figures, reasons, warnings = _figures_and_reasons(
            spec["name"],
            hint,
            run.results.get(spec["name"], {"status": "not-run"}),
            batch,
            batch // 2,
            deltas,
            th,
            spec["type"],
        )
        verdict.figures = figures
        verdict.reasons.extend(reasons)
        verdict.warnings.extend(warnings)
    for verdict in verdicts.values():
        verdict.passed = not verdict.reasons
    return SandboxReport(
        ok=all(v.passed for v in verdicts.values()),
        factors=verdicts,
        batch_size=batch,
        state_source=source,
        isolation=run.isolation,
        wall_seconds=time.monotonic() - started,
        worker_starts=run.starts,
        limits=limits,
        thresholds=th,
    )


def _batch_values(card: TaskCard, obs: np.ndarray) -> dict[str, np.ndarray]:
    values = card.feature_values(obs)
    values["obs"] = np.ascontiguousarray(obs)
    return values
