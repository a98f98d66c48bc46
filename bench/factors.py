"""Cost of evaluating the built-in factor programs (compiled, in-process) on batches of states.

    python bench/factors.py            # prints a Markdown table (µs per state)
"""

from __future__ import annotations

import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from mira.factors import example_program, example_programs
from mira.factors.evaluator import CompiledProgram
from mira.factors.sandbox import collect_states
from mira.tasks import load_task

ROOT = Path(__file__).resolve().parents[1]


def per_state_us(program_task: str, version: int, batch: int, repeats: int = 50) -> tuple[float, int]:
    card = load_task(program_task)
    states, actions = collect_states(card, max(batch, 512), seed=0)
    idx = np.arange(batch) % len(states)
    obs, act = states[idx], actions[idx]
    compiled = CompiledProgram(example_program(program_task, version), card)
    n = max(3, repeats if batch < 10_000 else 10)
    best = float("inf")
    for _ in range(n):
        t0 = time.perf_counter()
        view = card.state_view(obs)
        compiled.phi(view)
        compiled.aux(view, act)
        best = min(best, time.perf_counter() - t0)
    return best / batch * 1e6, len(compiled.phi_names) + len(compiled.aux_names)


def main() -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    print(f"Machine: {platform.machine()} {platform.processor()}, commit {commit}; best of repeated calls, "
          "state view + all PHI and AUX factors, 1 thread.\n")
    print("| program | factors | µs/state @ 1 | µs/state @ 256 | µs/state @ 10,000 |")
    print("|---|---|---|---|---|")
    for task, version in example_programs():
        cells = [per_state_us(task, version, b) for b in (1, 256, 10_000)]
        print(f"| {task} v{version} | {cells[0][1]} | " + " | ".join(f"{c[0]:.2f}" for c in cells) + " |")


if __name__ == "__main__":
    main()
