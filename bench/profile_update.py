"""Where one agent update spends its time.

    python bench/profile_update.py                          # SAC, 1 thread, HalfCheetah sizes, Table 1 nets
    python bench/profile_update.py --algo ddpg --threads 2
    python bench/profile_update.py --table --cprofile       # also torch.profiler's op table and cProfile

The update runs on a replay buffer of random transitions with HalfCheetah's sizes (obs 17, act 6),
batch 256 and 2x256 ReLU nets, so no simulator is needed. Printed:

1. the time per update with nothing attached: wall and this thread's CPU time, median of
   ``--trials`` blocks of ``--updates`` updates (on a shared machine read the CPU time);
2. **phases** (CPU time, measured by thin wrappers around the agent's building blocks): actor
   network forward / backward, squashed-Gaussian sampling forward / backward (SAC), critic forward /
   backward / input gradient through min-Q, Adam, and the rest of ``update`` (targets, losses,
   Polyak averaging, Python);
3. **op kinds** (torch.profiler self time, shares of the profiled time): matmuls (split by the phase
   they ran in), Adam kernels, Polyak, elementwise and other ops, autograd-engine overhead (if any
   autograd runs), and the Python / dispatch time between ops;
4. with ``--cprofile``, the Python functions with the most own time.

All numbers on a machine that others use are noisy: compare shares, or A/B within one process.
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import io
import os
import pstats
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algo", default="sac", choices=("sac", "ddpg"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--hidden", default="256,256")
    p.add_argument("--obs-dim", type=int, default=17)
    p.add_argument("--act-dim", type=int, default=6)
    p.add_argument("--updates", type=int, default=50, help="updates per timed block")
    p.add_argument("--trials", type=int, default=7, help="timed blocks (median reported)")
    p.add_argument("--table", action="store_true", help="also print torch.profiler's op table")
    p.add_argument("--cprofile", action="store_true", help="also print the top Python functions (cProfile)")
    return p.parse_args()


def _setup(args: argparse.Namespace) -> tuple[Any, Any, list[tuple[Any, Any]]]:
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # before torch starts its pools
    os.environ.setdefault("MKL_NUM_THREADS", str(args.threads))
    import numpy as np
    import torch

    from mira.agents import AgentConfig, make_agent
    from mira.replay import ReplayBuffer

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(20_000, args.obs_dim, args.act_dim)
    for t in range(5_000):
        buf.add(rng.normal(size=args.obs_dim), rng.uniform(-1, 1, args.act_dim), 0.0, float(rng.normal()),
                rng.normal(size=args.obs_dim), False, t % 1000 == 999, t // 1000)
    cfg = AgentConfig(batch_size=args.batch_size, hidden=tuple(int(h) for h in args.hidden.split(",")))
    agent = make_agent(args.algo, args.obs_dim, args.act_dim, cfg, torch.device("cpu"))
    batches = [buf.sample(args.batch_size, rng) for _ in range(args.updates)]
    work = [(b, buf.dense_reward[torch.from_numpy(b.indices)]) for b in batches]
    return torch, agent, work


# The agent's building blocks, by phase. Each entry: (module, attribute, phase label).
def _phase_targets() -> list[tuple[Any, str, str]]:
    from mira.agents import ddpg, networks, sac

    n = networks
    return [
        (n.MLPKernels, "forward", "actor net forward"),
        (n.MLPKernels, "backward", "actor net backward"),
        (n.EnsembleQKernels, "forward", "critic forward"),
        (n.EnsembleQKernels, "backward", "critic backward (critic loss)"),
        (n.EnsembleQKernels, "input_grad_of_min", "critic backward to the action (actor loss)"),
        (sac, "squashed_gaussian_forward", "squashed Gaussian forward"),
        (sac, "squashed_gaussian_backward", "squashed Gaussian backward"),
        (n.AdamStepper, "step", "Adam"),
        (ddpg, "relu_mlp", "actor net forward (act)"),
    ]


def _patch(wrapper: Callable[[Callable[..., Any], str], Callable[..., Any]]) -> Callable[[], None]:
    """Wrap every phase target with ``wrapper(fn, label)``; returns the undo function."""
    saved = []
    for owner, name, label in _phase_targets():
        fn = getattr(owner, name, None)
        if fn is None:
            continue
        saved.append((owner, name, fn))
        setattr(owner, name, wrapper(fn, label))

    def undo() -> None:
        for owner, name, fn in saved:
            setattr(owner, name, fn)

    return undo


MATMUL = {"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::mv", "aten::addmv", "aten::matmul",
          "aten::linear", "aten::linalg_vecdot", "mkldnn::_linear_pointwise"}


def _kind(ev: Any) -> str:
    name = ev.name
    chain = []
    p = ev.cpu_parent
    while p is not None:
        chain.append(p.name)
        p = p.cpu_parent
    phase = next((c for c in chain if c.startswith("phase: ")), None)
    if name in ("aten::_fused_adam_", "aten::_foreach_add_") or any(c.startswith("Optimizer.") for c in chain) \
            or name.startswith("Optimizer.") or phase == "phase: Adam":
        return "Adam (kernel + Python)"
    if name == "aten::_foreach_lerp_" or any("_foreach_lerp_" in c for c in chain):
        return "Polyak averaging"
    if name.startswith("phase: "):
        return "Python inside the phases"
    if name in MATMUL:
        return f"matmul — {phase[7:] if phase else 'outside the phases'}"
    in_bwd = any("Backward" in c or c.startswith("autograd::engine") for c in chain)
    if name.startswith("autograd::engine") or name.endswith(("Backward0", "Backward1")):
        return "autograd engine / nodes"
    return "elementwise & other ops" + (" (autograd backward)" if in_bwd else "")


def main() -> int:
    args = _parse()
    torch, agent, work = _setup(args)
    from torch.profiler import ProfilerActivity, profile, record_function

    def block() -> None:
        for batch, reward in work:
            agent.update(batch, reward)

    t0 = time.perf_counter()
    for batch, reward in work[:5]:
        agent.update(batch, reward)
    warm = time.perf_counter() - t0
    walls, cpus = [], []
    for _ in range(args.trials):
        w0, c0 = time.perf_counter(), time.thread_time()
        block()
        walls.append((time.perf_counter() - w0) / len(work) * 1e3)
        cpus.append((time.thread_time() - c0) / len(work) * 1e3)
    n = len(work)
    print(f"# {args.algo} update: batch {args.batch_size}, hidden {args.hidden}, threads {args.threads}, "
          f"torch {torch.__version__}, load average {os.getloadavg()[0]:.2f}")
    print(f"warm-up (5 updates): {warm:.2f} s")
    print(f"per update: wall median {statistics.median(walls):.2f} ms (min {min(walls):.2f}); "
          f"main-thread CPU median {statistics.median(cpus):.2f} ms (min {min(cpus):.2f})")

    # -- phases, CPU time (thread time at 1 thread; wall time otherwise, since the pool works too)
    clock = time.thread_time if args.threads == 1 else time.perf_counter
    spent: dict[str, float] = defaultdict(float)
    depth = [0]

    def timed(fn: Callable[..., Any], label: str) -> Callable[..., Any]:
        @functools.wraps(fn)
        def inner(*a: Any, **k: Any) -> Any:
            if depth[0]:
                return fn(*a, **k)
            depth[0] += 1
            t = clock()
            try:
                return fn(*a, **k)
            finally:
                spent[label] += clock() - t
                depth[0] -= 1

        return inner

    undo = _patch(timed)
    try:
        totals = []
        for _ in range(max(3, args.trials // 2)):
            t = clock()
            block()
            totals.append(clock() - t)
    finally:
        undo()
    reps = len(totals)
    total_ms = sum(totals) / reps / n * 1e3
    print(f"\n## phases ({'CPU' if args.threads == 1 else 'wall'} time per update, {reps} blocks of {n})")
    rows = sorted(((k, v / reps / n * 1e3) for k, v in spent.items()), key=lambda kv: -kv[1])
    rows.append(("rest of update (targets, losses, Polyak, Python)", total_ms - sum(v for _, v in rows)))
    for k, v in rows:
        print(f"{k:48s} {v:7.2f} ms {100 * v / total_ms:5.1f}%")
    print(f"{'total':48s} {total_ms:7.2f} ms")

    # -- op kinds, torch.profiler self time
    def labelled(fn: Callable[..., Any], label: str) -> Callable[..., Any]:
        @functools.wraps(fn)
        def inner(*a: Any, **k: Any) -> Any:
            with record_function(f"phase: {label}"):
                return fn(*a, **k)

        return inner

    undo = _patch(labelled)
    try:
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            w0 = time.perf_counter()
            block()
            prof_wall = (time.perf_counter() - w0) * 1e3
    finally:
        undo()
    events = [e for e in prof.events() if e.device_type.name == "CPU"]
    kinds: dict[str, float] = defaultdict(float)
    for ev in events:
        kinds[_kind(ev)] += ev.self_cpu_time_total / 1e3
    top = sum(ev.cpu_time_total for ev in events if ev.cpu_parent is None) / 1e3
    kinds["Python / dispatch between ops"] = max(prof_wall - top, 0.0)
    total = sum(kinds.values())
    print(f"\n## op kinds (torch.profiler self time; profiled {prof_wall / n:.2f} ms/update incl. its overhead)")
    for k, v in sorted(kinds.items(), key=lambda kv: -kv[1]):
        print(f"{k:58s} {v / n:7.2f} ms {100 * v / total:5.1f}%")
    mm = sum(v for k, v in kinds.items() if k.startswith("matmul"))
    print(f"{'all matmuls':58s} {mm / n:7.2f} ms {100 * mm / total:5.1f}%")

    if args.table:
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30))
    if args.cprofile:
        pr = cProfile.Profile()
        pr.enable()
        block()
        pr.disable()
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(20)
        print("\n## cProfile, sorted by own time (Python functions and builtins)")
        print(s.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
