"""MCM cost per outer cycle, as a fraction of the cycle's training wall time.

Measures, on realistic snapshot sizes (1,000 evaluation states, act_dim 17, a 1,000-transition RPE
batch, 5 factors) and a FULL healthy buffer (N_B = 128):

* ``metrics``  — raw diagnostics of one snapshot, including the tanh-squashed entropy estimate;
* ``diagnose`` — the whole ``MetacognitiveMonitor.diagnose`` call (metrics + standardisation +
  KDE score, threshold, bandwidth update, gating, trigger logic);
* ``trigger``  — the extra cost of the gradient and contributors on a triggering cycle.

A cycle of ΔT environment steps takes ``ΔT / steps_per_s`` seconds of training (default 100
steps/s ⇒ 50 s); the target is MCM ≤ 1% of that. Prints a Markdown table.

    python bench/mcm.py [--steps-per-s 100] [--delta-t 5000] [--repeats 50]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from mira.mcm import MCMConfig, MetacognitiveMonitor
from mira.mcm.records import CycleSnapshot

FACTORS = ["r_height", "r_survival", "r_stable", "r_explore", "r_vel"]


def make_snapshot(
    rng: np.random.Generator, step: int, n_eval: int, act_dim: int, batch: int, prev: CycleSnapshot | None
) -> CycleSnapshot:
    """A synthetic snapshot with the shapes a trainer produces (values are irrelevant to cost)."""
    value = rng.normal(size=n_eval)
    return CycleSnapshot(
        step=step,
        policy_mean=rng.normal(size=(n_eval, act_dim)),
        policy_log_std=rng.normal(scale=0.1, size=(n_eval, act_dim)) - 1.0,
        squashed=True,
        prev_policy_mean=None if prev is None else prev.policy_mean,
        prev_policy_log_std=None if prev is None else prev.policy_log_std,
        entropy=None,  # the monitor estimates the tanh-squashed entropy itself (counted in the cost)
        phi_eval=value + rng.normal(scale=0.5, size=n_eval),
        value_eval=value,
        attention_mean=dict(zip(FACTORS, rng.dirichlet(np.ones(len(FACTORS))), strict=True)),
        phi_s=rng.normal(size=batch),
        r_ext=(rng.random(batch) < 0.01) * rng.normal(size=batch) * 100.0,
        phi_next=rng.normal(size=batch),
        terminal=(rng.random(batch) < 0.001).astype(float),
        smoothed_return=float(step),  # rising: every cycle enters the buffer
    )


def _time_ms(fn: Callable[[], object], repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(samples)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps-per-s", type=float, default=100.0, help="training throughput (env steps/s)")
    ap.add_argument("--delta-t", type=int, default=5000, help="outer-cycle length ΔT in env steps")
    ap.add_argument("--n-eval", type=int, default=1000)
    ap.add_argument("--act-dim", type=int, default=17)
    ap.add_argument("--batch", type=int, default=1000, help="held-out transitions for d_RPE")
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    cfg = MCMConfig(delta_t=args.delta_t)
    mon = MetacognitiveMonitor(cfg)
    snaps: list[CycleSnapshot] = []
    prev = None
    for k in range(cfg.buffer_size + cfg.k_warm + args.repeats + 1):
        prev = make_snapshot(rng, (k + 1) * args.delta_t, args.n_eval, args.act_dim, args.batch, prev)
        snaps.append(prev)
    warm = cfg.buffer_size + cfg.k_warm
    for s in snaps[:warm]:
        mon.diagnose(s)
    assert mon.buffer_fill == cfg.buffer_size, "buffer must be full for a representative measurement"

    probe = snaps[warm]
    metrics_ms = _time_ms(lambda: mon.raw_metrics(probe), args.repeats)
    it = iter(snaps[warm:])
    diagnose_ms = _time_ms(lambda: mon.diagnose(next(it)), args.repeats)
    d = mon.standardizer.smoothed
    assert d is not None
    trigger_ms = _time_ms(lambda: mon.model.grad_log_density(d), args.repeats)

    per_cycle_ms = diagnose_ms + trigger_ms  # worst case: a triggering cycle
    cycle_s = args.delta_t / args.steps_per_s
    frac = per_cycle_ms / (cycle_s * 1e3)
    print(
        f"| N_eval | act_dim | N_B | metrics ms | diagnose ms | +trigger ms | cycle s "
        f"({args.steps_per_s:g} steps/s × ΔT={args.delta_t}) | MCM share | target |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {args.n_eval} | {args.act_dim} | {mon.buffer_fill} | {metrics_ms:.2f} | {diagnose_ms:.2f} | "
        f"{trigger_ms:.3f} | {cycle_s:g} | {100 * frac:.4f}% | {'ok' if frac <= 0.01 else 'OVER'} ≤ 1% |"
    )


if __name__ == "__main__":
    main()
