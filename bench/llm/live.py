"""``mira`` runs with an LLM in the loop, through the relay endpoint (``bench/llm/relay.py``).

Each job is one ``mira`` run (``mira sweep`` of one initial program and one seed) whose LLM is
``openai:MODEL`` at a relay of its own: every prompt of the run waits in ``QUEUES/<program>-s<seed>/``
until whoever plays the model answers it. An initial program is a flaw's name (``bench/flawed/<task>/
<name>.json``), a program file, or ``task`` (the task's own, which LSFS then asks the model for).
``--lanes`` runs go at a time; each run's queue gets ``DONE`` when the run ends, so the one answering
knows no more prompts come. The recorded exchanges stay in each run's ``llm/exchanges.jsonl``
(``mira llm export`` makes them a replayable script).

    python bench/llm/live.py --model claude-agent --programs no_progress,abs_velocity,wrong_gate,saturated_velocity \
        --seeds 0,1,2 --out bench/runs/llm_hc --queues /tmp/llmq/srr
    python bench/llm/live.py --model claude-agent --task humanoidstandup --steps 200000 --seeds 0 \
        --programs RUN/programs/v000.json --out bench/runs/llm_hs --queues /tmp/llmq/hs   # SRR only: a fixed v0
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from relay import Queue, serve

ROOT = Path(__file__).resolve().parents[2]


def program_file(name: str, task: str) -> str:
    """``task`` (the task's own program), a flaw of ``bench/flawed/<task>/``, or a program file."""
    if name == "task" or Path(name).suffix == ".json":
        return name
    return str(ROOT / "bench" / "flawed" / task / f"{name}.json")


def job(program: str, seed: int, port: int, args: argparse.Namespace) -> int:
    label = "task" if program == "task" else Path(program).stem
    queue = Queue(args.queues / f"{label}-s{seed}")
    server = serve(queue, port)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    train_args = (f"--llm openai:{args.model} --base-url http://127.0.0.1:{port}/v1 "
                  f"--set llm.timeout_s=3600 --set llm.max_retries=0 --threads 1")
    cmd = [sys.executable, "-m", "mira.cli", "sweep", "--tasks", args.task, "--programs",
           program_file(program, args.task), "--methods", "mira", "--algos", args.algo, "--seeds", f"{seed},",
           "--steps", str(args.steps), "--workers", "1", "--out", str(args.out), "--train-args", train_args]
    print(f"live: {label} s{seed} on port {port}, queue {queue.root}", flush=True)
    try:
        rc = subprocess.run(cmd, env={**os.environ, "OMP_NUM_THREADS": "1", "OPENAI_API_KEY": "unused"}).returncode
    finally:
        (queue.root / "DONE").write_text("done\n")
        server.shutdown()
    print(f"live: {label} s{seed} finished (exit {rc})", flush=True)
    return rc


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, help="the model name the runs record (openai:MODEL)")
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--algo", default="sac")
    p.add_argument("--programs", required=True,
                   help="comma-separated initial programs: flaw names, program files, or 'task'")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=100_000)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--queues", type=Path, required=True)
    p.add_argument("--lanes", type=int, default=2)
    p.add_argument("--port", type=int, default=8710, help="first port; each job takes the next")
    args = p.parse_args(argv)
    jobs = [(p, int(s)) for s in args.seeds.split(",") for p in args.programs.split(",")]
    with ThreadPoolExecutor(args.lanes) as pool:
        codes = list(pool.map(lambda ij: job(*ij[1], args.port + ij[0], args), enumerate(jobs)))
    return max(codes, default=0)


if __name__ == "__main__":
    sys.exit(main())
