"""Training throughput (environment steps per second once learning has started): MIRA's trainer
against Stable-Baselines3 with the same networks, batch and schedule, on HalfCheetah-v5.

    python bench/throughput.py                                  # SAC + DDPG, 1 and 2 threads, vs SB3
    python bench/throughput.py --algos sac --threads 1 --measure-steps 3000 --repeats 3
    python bench/throughput.py --methods dense,sparse,hars      # more rows through the same trainer
    python bench/throughput.py --no-write                       # print only

Every measurement runs in a fresh subprocess with ``OMP_NUM_THREADS``/``MKL_NUM_THREADS`` and
``torch.set_num_threads`` set to its thread count, so no setting leaks between configurations. The
configurations of one repeat run back to back (ours and SB3 alternate), and repeats are interleaved,
so a busy machine slows both sides alike; the table reports medians over repeats.

What is timed, for both sides: ``--measure-steps`` consecutive environment steps after
``--learning-starts`` uniform-random steps, each step being one action from the policy, one
environment step, one replay insert and one gradient step (train_freq 1, gradient_steps 1) on a
batch of 256, with 2x256 ReLU nets, lr 1e-4, gamma 0.99, tau 0.005 (Table 1). Ours runs the real
:class:`mira.loop.trainer.Trainer` with the method's reward source (``dense`` = ``DenseReward`` by
default); SB3 runs ``model.learn``. Evaluation and checkpointing fall outside the timed window.

Next to wall-clock steps/s each run reports steps per CPU-second of the process (``cpu_sps``), which
is much less sensitive to other jobs on the machine at 1 thread (at 2 threads it also counts the
second thread's work and spinning, so read it only as a cost figure), and the load average.

Other methods (``hars``, ``mira``, baselines) become extra rows with ``--methods``: each is run
through the same trainer, and the ``vs sparse`` column gives its steps/s relative to our ``sparse``
run of the same algorithm and thread count (add ``sparse`` to ``--methods`` to get that column).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "results.md"
SECTION = "## Speed"
SB3 = "sb3"


# ------------------------------------------------------------------------------------------ workers
def _busy_s() -> float:
    """CPU-seconds all processes have spent busy since boot (Linux /proc/stat; 0 elsewhere)."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return 0.0
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def _mark() -> tuple[float, float, float]:
    return time.perf_counter(), time.process_time(), _busy_s()


def _others_busy(seconds: float = 2.0) -> float:
    """Cores kept busy by other processes over ``seconds`` (this process sleeps meanwhile)."""
    b0, t0 = _busy_s(), time.perf_counter()
    time.sleep(seconds)
    return (_busy_s() - b0) / (time.perf_counter() - t0)


def _timing_hook(interval: int, marks: list[tuple[int, float, float, float]]) -> Any:
    """A trainer hook that records (step, wall, process CPU, machine busy) every ``interval`` steps."""

    class TimingHook:
        def __init__(self) -> None:
            self.interval = interval

        def on_cycle(self, ctx: Any) -> dict[str, float]:
            marks.append((ctx.step, *_mark()))
            return {}

        def state_dict(self) -> dict[str, Any]:
            return {}

        def load_state_dict(self, state: dict[str, Any]) -> None:
            return None

    return TimingHook()


def _window(marks: list[tuple[int, float, float, float]], start: int, steps: int) -> dict[str, float]:
    by_step = {m[0]: m[1:] for m in marks}
    if start not in by_step or start + steps not in by_step:
        raise RuntimeError(f"timing marks missing around [{start}, {start + steps}]: {sorted(by_step)[:5]}...")
    (w0, c0, b0), (w1, c1, b1) = by_step[start], by_step[start + steps]
    others = max((b1 - b0) - (c1 - c0), 0.0) / (w1 - w0)  # cores other processes kept busy meanwhile
    return {"sps": steps / (w1 - w0), "cpu_sps": steps / max(c1 - c0, 1e-9), "wall_s": w1 - w0,
            "others": round(others, 2)}


def worker_ours(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from mira.config import TrainConfig
    from mira.loop.trainer import Trainer, TrainSetup
    from mira.methods import build_method
    from mira.runio.rundir import RunDir, prepare_run_dir
    from mira.tasks.card import load_task

    torch.set_num_threads(args.threads)
    tmp = Path(tempfile.mkdtemp(prefix="mira-tp-"))
    try:
        cfg = TrainConfig(task=args.task, method=args.method, algo=args.algo, seed=args.seed,
                          learning_starts=args.learning_starts, threads=args.threads, device="cpu")
        cfg.agent.batch_size, cfg.agent.lr, cfg.agent.hidden = 256, 1e-4, (256, 256)
        total = args.learning_starts + args.measure_steps + args.interval  # the final eval falls outside
        cfg.steps = total
        path = prepare_run_dir(tmp / "run", resume=False, overwrite=False)
        card = load_task(cfg.task)
        run = RunDir(path)
        parts = build_method(cfg, card, path)
        marks: list[tuple[int, float, float, float]] = []
        cfg.eval_every, cfg.eval_episodes, cfg.checkpoint_every = 10 * total, 1, 10 * total
        cfg.max_episode_steps = None
        setup = TrainSetup(config=cfg, card=card, device=torch.device("cpu"), reward=parts.reward,
                           hooks=[*parts.hooks, _timing_hook(args.interval, marks)], quiet=True)
        load0 = os.getloadavg()[0]
        Trainer(setup, run).run()
        out = _window(marks, args.learning_starts, args.measure_steps)
        out["load"] = round((load0 + os.getloadavg()[0]) / 2, 2)
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def worker_sb3(args: argparse.Namespace) -> dict[str, Any]:
    import gymnasium as gym
    import numpy as np
    import torch
    from stable_baselines3 import DDPG, SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.noise import NormalActionNoise

    torch.set_num_threads(args.threads)
    marks: list[tuple[int, float, float, float]] = []

    class Timing(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % args.interval == 0:
                marks.append((self.num_timesteps, *_mark()))
            return True

    env = gym.make("HalfCheetah-v5")
    common = dict(learning_rate=1e-4, buffer_size=1_000_000, learning_starts=args.learning_starts, batch_size=256,
                  tau=0.005, gamma=0.99, train_freq=1, gradient_steps=1, seed=args.seed, device="cpu", verbose=0,
                  policy_kwargs=dict(net_arch=[256, 256]))
    if args.algo == "sac":
        model: Any = SAC("MlpPolicy", env, **common)
    else:
        n = env.action_space.shape[0]  # type: ignore[index]
        model = DDPG("MlpPolicy", env, action_noise=NormalActionNoise(np.zeros(n), 0.1 * np.ones(n)), **common)
    load0 = os.getloadavg()[0]
    model.learn(args.learning_starts + args.measure_steps + args.interval, callback=Timing())
    out = _window(marks, args.learning_starts, args.measure_steps)
    out["load"] = round((load0 + os.getloadavg()[0]) / 2, 2)
    return out


# -------------------------------------------------------------------------------------- the driver
def _run_one(kind: str, algo: str, threads: int, method: str, args: argparse.Namespace) -> dict[str, Any]:
    if args.wait_idle > 0:  # give other jobs a chance to finish: wait until they use < 0.3 cores
        deadline = time.perf_counter() + args.wait_idle
        while _others_busy() > 0.3 and time.perf_counter() < deadline:
            pass
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", kind, "--algo", algo, "--threads", str(threads),
           "--method", method, "--learning-starts", str(args.learning_starts), "--measure-steps",
           str(args.measure_steps), "--interval", str(args.interval), "--seed", str(args.seed), "--task", args.task]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT, timeout=args.run_timeout)
    except subprocess.TimeoutExpired:
        # Two intra-op threads on two cores shared with other jobs can slow a run down tenfold.
        return {"sps": float("nan"), "cpu_sps": float("nan"), "others": float("inf"), "load": os.getloadavg()[0],
                "total_s": round(time.perf_counter() - t0, 1), "timeout": True}
    if proc.returncode != 0:
        raise RuntimeError(f"{kind} {algo} t{threads} {method} failed:\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    res = json.loads(line[len("RESULT "):])
    res["total_s"] = round(time.perf_counter() - t0, 1)
    return res


def _machine() -> dict[str, str]:
    info = {"cpu": platform.processor() or platform.machine(), "cores": str(os.cpu_count())}
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        fields = dict(re.findall(r"^([^:\n]+):\s*(.*)$", out, re.M))
        info["cpu"] = fields.get("Model name", info["cpu"]).strip()
        cores = int(fields.get("Core(s) per socket", "0")) * int(fields.get("Socket(s)", "1"))
        info["cores"] = f"{fields.get('CPU(s)', '?').strip()} CPUs ({cores} cores, "
        info["cores"] += f"{fields.get('Thread(s) per core', '?').strip()} thread/core)"
        if "Hypervisor vendor" in fields:
            info["cores"] += f", VM ({fields['Hypervisor vendor'].strip()})"
    except (OSError, subprocess.CalledProcessError, ValueError):
        pass
    try:
        info["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                        cwd=ROOT, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        info["commit"] = "unknown"
    import torch

    info["torch"] = torch.__version__
    try:
        import stable_baselines3

        info["sb3"] = stable_baselines3.__version__
    except ImportError:
        info["sb3"] = "not installed"
    info["python"] = platform.python_version()
    return info


def _load_line(loads: list[float], others: list[float]) -> str:
    if not loads or not others:
        return ""
    return (f"- load average during the runs: min {min(loads):.1f}, median {statistics.median(loads):.1f}, max "
            f"{max(loads):.1f}; CPU used by other processes during the timed windows: median "
            f"{statistics.median(others):.2f} cores, max {max(others):.2f} (of {os.cpu_count()})")


def _fmt(x: float | None, digits: int = 1) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def _clean(run: dict[str, Any], limit: float) -> bool:
    return not run.get("timeout") and run.get("others", 0.0) <= limit


def _paired(a: list[dict[str, Any]], b: list[dict[str, Any]], limit: float) -> tuple[float | None, int, int]:
    """Median over repeats of a[r].sps / b[r].sps, using only repeats where neither run was disturbed
    (runs of one repeat are adjacent in time, so the machine's state is as similar as it gets)."""
    pairs = [(x, y) for x, y in zip(a, b, strict=False)]
    ratios = [x["sps"] / y["sps"] for x, y in pairs if _clean(x, limit) and _clean(y, limit)]
    return (statistics.median(ratios) if ratios else None), len(ratios), len(pairs)


def _median_sps(rows: list[dict[str, Any]], limit: float, key: str = "sps") -> float | None:
    clean = [r[key] for r in rows if _clean(r, limit)]
    return statistics.median(clean) if clean else None


def build_table(results: dict[tuple[str, str, int, str], list[dict[str, Any]]], args: argparse.Namespace,
                machine: dict[str, str]) -> str:
    lim = args.disturbed
    lines = [
        "| algo | threads | method | ours steps/s | SB3 steps/s | ours / SB3 | clean pairs | vs sparse "
        "| ours steps per CPU-s | SB3 steps per CPU-s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for algo in args.algos:
        for threads in args.threads:
            sb3 = results.get((SB3, algo, threads, "-"), [])
            sparse = results.get(("ours", algo, threads, "sparse"), [])
            for method in args.methods:
                ours = results.get(("ours", algo, threads, method), [])
                ratio, k, n = _paired(ours, sb3, lim) if sb3 else (None, 0, 0)
                vs_sparse = _paired(ours, sparse, lim)[0] if sparse and method != "sparse" else None
                lines.append(
                    f"| {algo} | {threads} | {method} | {_fmt(_median_sps(ours, lim))} | {_fmt(_median_sps(sb3, lim))} "
                    f"| {_fmt(ratio, 2)}{'×' if ratio else ''} | {k}/{n} | {_fmt(vs_sparse, 2)} "
                    f"| {_fmt(_median_sps(ours, lim, 'cpu_sps'))} | {_fmt(_median_sps(sb3, lim, 'cpu_sps'))} |")
    loads = [r["load"] for rs in results.values() for r in rs if "load" in r]
    others = [r["others"] for rs in results.values() for r in rs if "others" in r and not r.get("timeout")]
    per_run = []
    for (kind, algo, threads, method), rs in sorted(results.items()):
        name = f"{kind} {algo} t{threads}" + (f" {method}" if kind == "ours" else "")
        per_run.append(f"{name}: " + ", ".join(
            ("timed out" if r.get("timeout") else f"{r['sps']:.1f}")
            + ("" if _clean(r, lim) else " (disturbed)") + (f" after {r['retried']} retry" if r.get("retried") else "")
            + f" [others {r.get('others', float('nan')):.2f} cores, load {r['load']:.1f}]" for r in rs))
    head = [
        f"Measured {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} with `python bench/throughput.py "
        f"{' '.join(args.argv)}`",
        "",
        f"- machine: {machine['cpu']}, {machine['cores']}; torch {machine['torch']}, SB3 {machine['sb3']}, "
        f"Python {machine['python']}; commit `{machine['commit']}`",
        f"- HalfCheetah-v5, {args.learning_starts} random steps, then {args.measure_steps} timed training steps "
        f"(1 env step + 1 gradient step each, batch 256, 2x256 nets, lr 1e-4); {args.repeats} repeat(s), each "
        f"running every configuration once, ours and SB3 back to back",
        _load_line(loads, others),
        f"- a run is *disturbed* when other processes kept more than {lim} cores busy during its timed window "
        f"(2 intra-op threads on 2 shared cores collapse then); steps/s are medians over undisturbed runs, "
        f"ours / SB3 is the median over repeats of the ratio of the two adjacent runs, undisturbed pairs only",
        "- steps per CPU-s: per CPU-second of the whole process (robust to other jobs at 1 thread; at 2 threads "
        "it counts both threads, spinning included)",
        "",
    ]
    return "\n".join(head + lines + ["", "<details><summary>every run (steps/s)</summary>", ""]
                     + [f"- {p}" for p in per_run] + ["", "</details>", ""])


def write_section(table: str) -> None:
    """Replace the measured table inside the Speed section of the results page (between markers),
    leaving everything else in the file (other sections, the hand-written notes) alone."""
    begin, end = "<!-- throughput:begin -->", "<!-- throughput:end -->"
    block = f"{begin}\n{table}{end}"
    text = PAGE.read_text(encoding="utf-8") if PAGE.exists() else "# Benchmark results\n"
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end):]
    elif SECTION in text:
        i = text.index(SECTION) + len(SECTION)
        text = text[:i] + "\n\n" + block + "\n" + text[i:]
    else:
        text = text.rstrip("\n") + f"\n\n{SECTION}\n\n{block}\n"
    PAGE.write_text(text, encoding="utf-8")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algos", default="sac,ddpg")
    p.add_argument("--threads", default="1,2")
    p.add_argument("--methods", default="dense", help="our reward methods, comma-separated (rows of the table)")
    p.add_argument("--learning-starts", type=int, default=1000)
    p.add_argument("--measure-steps", type=int, default=2000)
    p.add_argument("--interval", type=int, default=50, help="timing-mark interval (divides the two above)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--disturbed", type=float, default=0.25, metavar="CORES",
                   help="a run is disturbed when other processes used more than this many cores meanwhile")
    p.add_argument("--retries", type=int, default=1, help="re-run a disturbed run up to this many times")
    p.add_argument("--run-timeout", type=float, default=240.0, metavar="S",
                   help="give up on a run after S seconds (counted as disturbed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--no-sb3", action="store_true", help="only our trainer")
    p.add_argument("--wait-idle", type=float, default=0.0, metavar="S",
                   help="before each run, wait up to S seconds for other processes to use < 0.3 cores")
    p.add_argument("--no-write", action="store_true", help="print the table, leave docs/results.md alone")
    p.add_argument("--json", default=None, help="also dump every run's numbers to this file")
    # internal: one measurement in this process
    p.add_argument("--worker", choices=("ours", SB3), help=argparse.SUPPRESS)
    p.add_argument("--algo", default="sac", help=argparse.SUPPRESS)
    p.add_argument("--method", default="dense", help=argparse.SUPPRESS)
    argv = sys.argv[1:]
    args = p.parse_args(argv)
    if args.worker:
        args.threads = int(args.threads)
        res = worker_ours(args) if args.worker == "ours" else worker_sb3(args)
        print("RESULT " + json.dumps(res), flush=True)
        return 0

    args.argv = argv
    args.algos = [a for a in args.algos.split(",") if a]
    args.threads = [int(t) for t in args.threads.split(",") if t]
    args.methods = [m for m in args.methods.split(",") if m]
    if args.learning_starts % args.interval or args.measure_steps % args.interval:
        p.error("--interval must divide --learning-starts and --measure-steps")
    machine = _machine()
    plan: list[tuple[str, str, int, str]] = []
    for algo in args.algos:
        for threads in args.threads:
            for method in args.methods:
                plan.append(("ours", algo, threads, method))
            if not args.no_sb3:
                plan.append((SB3, algo, threads, "-"))
    results: dict[tuple[str, str, int, str], list[dict[str, Any]]] = {k: [] for k in plan}
    print(f"# {machine}", flush=True)
    for rep in range(args.repeats):
        order = plan if rep % 2 == 0 else plan[::-1]  # alternate who goes first
        for kind, algo, threads, method in order:
            tries = []
            for _ in range(1 + args.retries):
                res = _run_one(kind, algo, threads, method if kind == "ours" else "dense", args)
                tries.append(res)
                print(f"[{rep + 1}/{args.repeats}] {kind:4s} {algo:4s} t{threads} {method:6s} {res['sps']:7.1f} "
                      f"steps/s (cpu {res['cpu_sps']:6.1f}/s, others {res['others']:.2f} cores, load "
                      f"{res['load']:.2f}, run {res['total_s']:.0f} s)", flush=True)
                if _clean(res, args.disturbed):
                    break
            res = dict(tries[-1], retried=len(tries) - 1)
            results[(kind, algo, threads, method)].append(res)
    table = build_table(results, args, machine)
    print("\n" + table)
    if args.json:
        Path(args.json).write_text(json.dumps({f"{k[0]}|{k[1]}|{k[2]}|{k[3]}": v for k, v in results.items()},
                                              indent=1), encoding="utf-8")
    if not args.no_write:
        write_section(table)
        print(f"wrote the table into {PAGE.relative_to(ROOT)} ({SECTION})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
