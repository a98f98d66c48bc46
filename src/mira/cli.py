"""The ``mira`` command line.

Bad input (flags, task cards, program files, sweep files) is reported on one line with exit status 2
and no traceback; a run that fails for lack of disk space stops with exit status 1 and a resumable
state.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import platform
import shutil
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tqdm.contrib.logging import logging_redirect_tqdm

from mira.cli_types import Parser, nonneg_int, positive_int
from mira.config import TrainConfig, apply_override, drop_removed_fields, from_dict, to_dict
from mira.errors import DiskFullError, Interrupted, MiraError, NonFiniteError, UsageError
from mira.loop.stop import sigterm_interrupts
from mira.methods import build_method
from mira.tasks.card import card_to_dict, load_task
from mira.train_cli import add_llm_flags, add_train_arguments, config_from_args, describe_config
from mira.version import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mira", description="LLM-written reward factors, revised while the agent learns.")
    parser.add_argument("--version", action="version", version=f"mira {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)

    t = sub.add_parser("train", help="train one run (one task, method, algo, seed)")
    add_train_arguments(t)

    f = sub.add_parser("factors", help="reward-factor programs: synthesise, check")
    fsub = f.add_subparsers(dest="factors_command", required=True, parser_class=Parser)
    fs = fsub.add_parser("synth", help="print (or write) the initial factor program of a task (LSFS)")
    fs.add_argument("--task", required=True)
    fs.add_argument("--out", default=None, help="write the program JSON here instead of printing it")
    add_llm_flags(fs)
    fc = fsub.add_parser("check", help="static and sandbox checks; exit 0 if admissible, 1 with reasons if not")
    fc.add_argument("program", help="factor-program JSON file")
    fc.add_argument("--task", required=True)
    fc.add_argument("--no-sandbox", action="store_true", help="static checks only")

    from mira.experiments.cli import add_report_parser, add_sweep_parser

    add_sweep_parser(sub)
    add_report_parser(sub)

    e = sub.add_parser("explain", help="the story of a run: versions, interventions, evidence, what changed")
    e.add_argument("run_dir")

    ev = sub.add_parser("eval", help="run a trained policy: mean ± std return of deterministic episodes, videos",
                        description="Play the deterministic policy of RUN_DIR/policy.pt (or --best: policy_best.pt, "
                                    "or a policy file) on its task's environment, as the run's evaluations do, and "
                                    "print the mean ± std return. By default the episodes are the run's own "
                                    "evaluation episodes, so the figure repeats eval.csv's.")
    ev.add_argument("target", metavar="RUN_DIR_OR_POLICY")
    ev.add_argument("--episodes", type=positive_int, default=None,
                    help="episodes to play (default: as many as each of the run's evaluations)")
    ev.add_argument("--seed", type=nonneg_int, default=None,
                    help="episode k starts from seed S+k (default: the run's evaluation seeds)")
    ev.add_argument("--best", action="store_true", help="RUN_DIR/policy_best.pt (the best evaluation's policy)")
    ev.add_argument("--video", default=None, metavar="DIR",
                    help="record every episode as an MP4 in DIR (headless: EGL or OSMesa, see docs/using_policies.md)")

    lm = sub.add_parser("llm", help="a run's exchanges with its reward engineer")
    lmsub = lm.add_subparsers(dest="llm_command", required=True, parser_class=Parser)
    lx = lmsub.add_parser("export", help="write a run's LLM replies as a replayable script or response cache",
                          description="Write the replies of RUN_DIR/llm/exchanges.jsonl as a script for "
                                      "--llm script:FILE (default) or as a response cache for --llm-cache DIR "
                                      "--llm-offline-only. Exchanges without a reply are skipped and counted.")
    lx.add_argument("run_dir", metavar="RUN_DIR")
    lx.add_argument("--out", default=None, metavar="FILE|DIR",
                    help="script file (default RUN_DIR/llm/script.jsonl) or cache directory (required)")
    lx.add_argument("--format", choices=("script", "cache"), default="script", help="default: script")
    return parser


def environment_facts() -> dict[str, Any]:
    import gymnasium
    import mujoco
    import numpy

    from mira.agents import gemm

    return {"mira": __version__, "python": platform.python_version(), "torch": torch.__version__,
            "gemm_backend": gemm.backend(),  # the agents' float32 products: rerun with MIRA_GEMM set to this
            "numpy": numpy.__version__, "gymnasium": gymnasium.__version__, "mujoco": mujoco.__version__,
            **source_revision(), "platform": platform.platform(), "cpu": cpu_model(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(), "argv": sys.argv}


def cpu_model() -> str:
    """The CPU's model name. A run's float rounding depends on it (each CPU model gets its own GEMM
    and vector kernels), so the same seed reproduces a run exactly only on the same kind of CPU."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


SOURCE_ROOT = Path(__file__).resolve().parents[2]
"""Where a checkout of mira has its ``.git``: two levels above this package (``src/mira``)."""


def source_revision(root: Path = SOURCE_ROOT) -> dict[str, str | None]:
    """``source``: the git commit of the checkout mira runs from (an editable install), and
    ``source_tree``: the id of its ``src/`` tree at that commit (the same across commits that change only
    docs or benchmarks), each with ``+`` and a digest of ``git diff HEAD -- src`` when the code differs
    from it; both None when there is no checkout (a wheel) or git cannot answer. Recorded in a run's
    ``config.json``: the commit traces a figure to the code that produced it, the tree tells a resume
    at other code."""
    unknown: dict[str, str | None] = {"source": None, "source_tree": None}
    if not (root / ".git").exists() or not (root / "src" / "mira").is_dir():
        return unknown

    def git(*argv: str) -> bytes:
        return subprocess.run(["git", "-C", str(root), *argv], capture_output=True, check=True, timeout=30).stdout

    try:
        head, tree = git("rev-parse", "HEAD", "HEAD:src").decode().split()
        diff = git("diff", "HEAD", "--", "src")
    except (OSError, subprocess.SubprocessError, ValueError):
        return unknown
    changes = f"+{hashlib.sha256(diff).hexdigest()[:12]}" if diff else ""
    return {"source": head + changes, "source_tree": tree + changes}


# What decides a run's arithmetic besides its configuration and seed: a resumed run that differs in
# any of them is still a valid run, but no longer the bit-for-bit continuation of the original.
REPRODUCIBILITY_KEYS = ("cpu", "cpu_capability", "torch", "gemm_backend", "source_tree")


def reproducibility_drift(recorded: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """``"key: recorded -> now"`` for every :data:`REPRODUCIBILITY_KEYS` entry that changed (keys a
    run directory does not record, from older versions, are skipped)."""
    return [f"{key}: {recorded[key]!r} -> {now.get(key)!r}" for key in REPRODUCIBILITY_KEYS
            if key in recorded and recorded[key] != now.get(key)]


def record_resume(path: Path, drift: list[str], facts: dict[str, Any]) -> None:
    """Record in ``config.json`` (under ``"resumed_elsewhere"``) a resume on another machine, software or
    source: the step it continued from, what changed and the facts of where it continued, so that the run's
    figures after that step are not read as the recorded source's."""
    from mira.runio.checkpoint import list_checkpoints
    from mira.runio.rundir import RunDir

    saved = json.loads((path / "config.json").read_text(encoding="utf-8"))
    entry = {"step": max(list_checkpoints(path / "checkpoints"), default=0), "drift": drift,
             "environment": facts}
    RunDir(path).write_config({**saved, "resumed_elsewhere": [*saved.get("resumed_elsewhere", []), entry]})


def extend_budget(path: Path, saved: dict[str, Any], cfg: TrainConfig, steps: int) -> TrainConfig:
    """``--resume DIR --steps N``: the run's configuration with the larger budget ``N``, recorded in its
    ``config.json`` (with the budgets it had before, under ``"extended_from"``).

    Nothing else in a run depends on its budget except the replay capacity (``min(buffer_size, steps)``),
    which the buffer grows on restore, so a run extended at an episode boundary continues as a run started
    with the larger budget would have. A budget below the steps already taken is refused.
    """
    from mira.runio.checkpoint import list_checkpoints
    from mira.runio.rundir import RunDir

    done = max(list_checkpoints(path / "checkpoints"), default=0)
    if steps < max(done, cfg.steps):
        raise UsageError(f"--resume {path} --steps {steps}: the run's budget is {cfg.steps} and it has reached "
                         f"step {done}; --steps can only extend it")
    extended = dataclasses.replace(cfg, steps=steps)
    RunDir(path).write_config({**saved, "config": to_dict(extended),
                               "extended_from": [*saved.get("extended_from", []), cfg.steps]})
    logging.getLogger(__name__).info("%s: budget extended from %d to %d steps", path, cfg.steps, steps)
    return extended


FORK_FIXED = ("task", "algo", "learning_starts", "buffer_size", "batch_size", "lr", "preset", "hidden", "eval_every",
              "eval_episodes", "checkpoint_every", "log_every", "max_episode_steps", "program")
"""Flags a fork cannot change: they decide what the checkpoint holds (networks, buffer, program v0) or how the
run is measured, so a fork with them changed could not load the checkpoint or be compared with its parent."""
FORK_SETTABLE = ("mira.", "llm.", "hars.", "agent.target_entropy")
"""The ``--set`` sections (and fields) a fork may change: the outer loop, the reward engineer, the shaping
and SAC's target entropy (how random the policy is kept: an exploration setting, not a network's shape)."""


def prepare_fork(args: argparse.Namespace) -> tuple[Path, TrainConfig, dict[str, Any]]:
    """``--fork PARENT --out DIR``: the fork's directory (:mod:`mira.runio.fork`), its configuration (the
    parent's with the fork's changes) and its ``forked_from`` record for ``config.json``."""
    from mira.methods import fork_compatible
    from mira.runio.checkpoint import checkpoint_files
    from mira.runio.fork import copy_fork_files, fork_checkpoint, program_version_at
    from mira.runio.rundir import prepare_run_dir
    from mira.train_cli import train_parser

    parent = Path(args.fork)
    if args.resume or args.out is None:
        raise UsageError("--fork RUN_DIR starts a new run: give it --out DIR (and no --resume)")
    out, source = Path(args.out).resolve(), parent.resolve()
    if out == source or out in source.parents or source in out.parents:
        raise UsageError(f"--fork {parent} --out {args.out}: the fork's directory cannot be the parent's, inside "
                         "it or around it")
    defaults = train_parser().parse_args([])
    fixed = [f"--{name.replace('_', '-')}" for name in FORK_FIXED if getattr(args, name) != getattr(defaults, name)]
    fixed += [f"--set {a}" for a in args.overrides if not a.split("=", 1)[0].strip().startswith(FORK_SETTABLE)]
    if fixed:
        settable = ", ".join(p + "*" if p.endswith(".") else p for p in FORK_SETTABLE)
        raise UsageError(f"--fork {parent}: a fork continues its parent's networks, buffer and evaluations, so "
                         f"{', '.join(fixed)} cannot change; it takes --seed, --steps, --method, the LLM flags, "
                         f"--threads, --device and --set {settable}")
    try:
        saved = json.loads((parent / "config.json").read_text(encoding="utf-8"))
        cfg: TrainConfig = from_dict(TrainConfig, drop_removed_fields(saved["config"], f"--fork {parent}: config.json"))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"--fork {parent}: not a usable run directory ({exc})") from exc
    method = cfg.method if args.method is None else args.method
    if not fork_compatible(cfg.method, method):
        raise UsageError(f"--fork {parent} --method {method}: a {cfg.method} checkpoint does not continue as {method}")
    program = fork_program(args.fork_program, method, cfg.task) if args.fork_program else None
    step, state = fork_checkpoint(parent, args.fork_step)
    steps = cfg.steps if args.steps is None else args.steps
    if steps <= step:
        raise UsageError(f"--fork {parent}: the checkpoint is at step {step}; --steps {steps} leaves nothing to train")
    cfg = dataclasses.replace(cfg, method=method, steps=steps, seed=cfg.seed if args.seed is None else args.seed,
                              threads=args.threads, device=args.device)
    for flag, key in (("llm", "backend"), ("base_url", "base_url"), ("api_key_env", "api_key_env"),
                      ("llm_cache", "cache_dir"), ("llm_offline_only", "offline_only")):
        if getattr(args, flag) != getattr(defaults, flag):
            setattr(cfg.llm, key, getattr(args, flag))
    for assignment in args.overrides:
        apply_override(cfg, assignment)
    path = prepare_run_dir(args.out, resume=False, overwrite=args.overwrite)
    try:
        copy_fork_files(parent, step, path, program_version_at(state))
    except OSError as exc:
        shutil.rmtree(path, ignore_errors=True)
        raise UsageError(f"--fork {parent}: cannot copy its checkpoint to {path} ({exc})") from exc
    manifest = json.loads(checkpoint_files(path / "checkpoints", step)[1].read_text(encoding="utf-8"))
    forked_from = {"run": str(parent.resolve()), "step": step, "sha256": manifest["sha256"],
                   "seed": saved["config"].get("seed"), "method": saved["config"].get("method"),
                   "source": (saved.get("environment") or {}).get("source")}
    if args.overrides:
        forked_from["settings"] = [a.strip() for a in args.overrides]  # what the fork changed: the arm of a pair
    if program is not None:
        forked_from["program_file"] = str(Path(args.fork_program).resolve())
        forked_from["program"] = program.to_json()  # a resume before the fork's first checkpoint installs it again
    return path, cfg, forked_from


def fork_program(path: str, method: str, task: str) -> Any:
    """``--fork-program FILE``: the program, checked as an LLM's would be (static checks and the sandbox)."""
    from mira.engineer.admission import admit_program
    from mira.factors.program import load_program
    from mira.methods import FORK_FAMILIES

    if not any(method in family and "mira" in family for family in FORK_FAMILIES):
        raise UsageError(f"--fork-program {path}: only a mira method installs programs while it trains, not {method}")
    program = load_program(path)
    card = load_task(task)
    if program.task != card.name:
        raise UsageError(f"--fork-program {path}: a program for task {program.task!r}, not {card.name!r}")
    gates = admit_program(program, card)
    if not gates.ok:
        raise UsageError(f"--fork-program {path}: not admissible: " + "; ".join(gates.errors))
    return program


def installed_at_fork(forked_from: dict[str, Any] | None) -> Any:
    """The program a fork installs at its start (recorded in its ``config.json``), or None."""
    if not forked_from or forked_from.get("program") is None:
        return None
    from mira.factors.program import FactorProgram

    return FactorProgram.from_json(forked_from["program"])


def cmd_train(args: argparse.Namespace) -> int:
    from mira.agents import gemm
    from mira.loop.trainer import Trainer, TrainSetup, resolve_device
    from mira.runio.rundir import RunDir, prepare_run_dir
    from mira.tasks.envs import action_dim

    gemm.backend()  # a bad MIRA_GEMM is a usage error before anything is written
    if args.show_config:
        if args.resume or args.fork:
            raise UsageError("--show-config describes a new run's configuration; a run's own is in RUN_DIR/config.json")
        print(describe_config(config_from_args(args)))
        return 0
    forked_from: dict[str, Any] | None = None
    cfg: TrainConfig
    if args.fork_program and not args.fork:
        raise UsageError("--fork-program FILE installs a program at a fork: give --fork RUN_DIR too")
    if args.fork:
        path, cfg, forked_from = prepare_fork(args)
        card = load_task(cfg.task)
    elif args.resume:
        path = prepare_run_dir(args.resume, resume=True, overwrite=False)
        try:
            saved = json.loads((path / "config.json").read_text(encoding="utf-8"))
            settings = drop_removed_fields(saved["config"], f"--resume {path}: config.json")
            cfg = from_dict(TrainConfig, settings)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise UsageError(f"--resume {path}: config.json is unusable ({exc})") from exc
        if args.steps is not None and args.steps != cfg.steps:
            cfg = extend_budget(path, saved, cfg, args.steps)
        card = load_task(cfg.task)
        facts = environment_facts()
        drift = reproducibility_drift(saved.get("environment") or {}, facts)
        if drift:
            logging.getLogger(__name__).warning(
                "--resume %s on a different machine, software or source (%s): the run continues from its checkpoint, "
                "but not bit for bit as it would have where it started", path, "; ".join(drift))
            record_resume(path, drift, facts)
        forked_from = saved.get("forked_from")
    else:
        if args.out is None:
            raise UsageError("train: --out DIR is required (or --resume DIR)")
        # Everything that can be checked without a run directory is checked before one exists: a bad
        # flag, task card or environment leaves nothing on disk.
        cfg = config_from_args(args)
        card = load_task(cfg.task)
        action_dim(card)  # builds the environment once: the card's indices and action names
        if cfg.learning_starts >= cfg.steps and cfg.method != "sparse":
            logging.getLogger(__name__).warning("learning_starts >= steps: the agent will never update")
        path = prepare_run_dir(args.out, resume=False, overwrite=args.overwrite)
    run = RunDir(path)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    try:
        parts = build_method(cfg, card, path)
        if not args.resume:
            run.write_config({"config": to_dict(cfg), "task_card": card_to_dict(card),
                              "method": {"description": parts.description, **parts.reward.describe()},
                              "environment": environment_facts(),
                              **({"forked_from": forked_from} if forked_from else {})})
        # Without a terminal (a log file, a pipe) progress comes as plain lines, never as a redrawn bar.
        quiet = bool(args.quiet) or not sys.stderr.isatty()
        setup = TrainSetup(config=cfg, card=card, device=resolve_device(cfg.device), reward=parts.reward,
                           hooks=parts.hooks, quiet=quiet, fork_step=forked_from["step"] if forked_from else None,
                           fork_program=installed_at_fork(forked_from))
        trainer = Trainer(setup, run)
    except BaseException:
        if not args.resume:
            # The run never started (e.g. the reward engineer's program was refused): nothing of it is
            # worth keeping, and a directory without a config would block both a rerun and --resume.
            shutil.rmtree(path, ignore_errors=True)
        raise
    try:
        with contextlib.nullcontext() if quiet else logging_redirect_tqdm():  # event lines above the bar
            result = trainer.run()
    except DiskFullError as exc:
        print(f"mira: {exc}; the run stopped at its last checkpoint and can be resumed with --resume {path}",
              file=sys.stderr)
        return 1
    except NonFiniteError as exc:
        run.set_status("failed", trainer.step, str(exc))
        print(f"mira: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGINT)
        name = signal.Signals(signum).name
        kept = (f"checkpoint at step {exc.step}" if isinstance(exc, Interrupted) and exc.checkpointed
                else "its last checkpoint is kept")
        run.set_status("interrupted", trainer.step, f"stopped by {name} ({kept}); resume with --resume")
        print(f"\nmira: stopped by {name} at step {trainer.step} ({kept}); resume with: mira train --resume {path}",
              file=sys.stderr)
        return 128 + signum
    except Exception as exc:
        run.set_status("failed", trainer.step, f"{type(exc).__name__}: {exc}")
        print(f"mira: the run failed at step {trainer.step}; after fixing the cause, continue it with "
              f"mira train --resume {path} (from its last checkpoint, or from the start if it has none)",
              file=sys.stderr)
        raise
    final = "" if result.final_eval is None else f", final eval return {result.final_eval.mean:.2f}"
    print(f"mira: finished {result.steps} steps in {result.wall_s:.1f} s{final}; run directory {path}")
    return 0


def _default_cache() -> Path:
    return Path(os.environ.get("MIRA_CACHE_DIR", Path.home() / ".cache" / "mira" / "llm"))


def cmd_factors(args: argparse.Namespace) -> int:
    if args.factors_command == "check":
        from mira.factors.cli_impl import check_program_file

        return check_program_file(args.program, args.task, sandbox=not args.no_sandbox)
    from mira.engineer.lsfs import backend_from_config, synthesize_program
    from mira.factors.program import save_program
    from mira.llm.config import LLMConfig
    from mira.tasks.envs import action_dim

    card = load_task(args.task)
    llm = LLMConfig(backend=args.llm, base_url=args.base_url, api_key_env=args.api_key_env,
                    cache_dir=args.llm_cache, offline_only=args.llm_offline_only)
    made = synthesize_program(card, backend_from_config(llm, _default_cache(), None), action_dim(card),
                              followups=llm.followups)
    program = made.program
    if made.retries:
        print(f"mira: the program was admitted on attempt {len(made.attempts)} (the earlier replies were sent back "
              "with their errors)", file=sys.stderr)
    for warning in made.warnings:
        print(warning, file=sys.stderr)
    if args.out:
        save_program(program, args.out)
        print(f"mira: wrote {args.out} ({len(program.factors)} factors)", file=sys.stderr)
    else:
        print(json.dumps(program.to_json(), indent=2))
    return 0


def cmd_explain(args: argparse.Namespace) -> int:
    from mira.explain import explain

    print(explain(args.run_dir))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from mira.agents.policy_file import load_policy
    from mira.loop.playback import evaluate_policy

    policy = load_policy(args.target, best=args.best)
    print(f"mira eval: {policy.path}: {policy.describe()}")
    result = evaluate_policy(policy, episodes=args.episodes, seed=args.seed, video_dir=args.video)
    print(f"mira eval: {result.summary()}")
    for video in result.videos:
        print(f"mira eval: video {video}")
    return 0


def cmd_llm(args: argparse.Namespace) -> int:
    from mira.llm.export import export_run

    print(export_run(args.run_dir, args.out, args.format).summary())
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # A training run reports its events (evaluations with --quiet, the monitor's triggers, SRR's candidates
    # and decisions) as INFO lines; other commands only warn.
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if getattr(args, "command", None) == "train" or getattr(args, "quiet", False):
        logging.getLogger("mira").setLevel(logging.INFO)
    handlers = {"train": cmd_train, "factors": cmd_factors, "explain": cmd_explain, "eval": cmd_eval, "llm": cmd_llm}
    try:
        handler = handlers.get(args.command) or args.func
        with sigterm_interrupts():  # `kill PID` stops a command as Ctrl-C does
            result: int = handler(args)
        return result
    except KeyboardInterrupt as exc:  # before a run started, or a command without a run
        signum = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGINT)
        print(f"mira {args.command}: stopped by {signal.Signals(signum).name}", file=sys.stderr)
        return 128 + signum
    except UsageError as exc:
        print(f"mira {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MiraError as exc:
        print(f"mira {args.command}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
