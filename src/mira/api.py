"""MIRA from Python: :func:`train` is ``mira train`` as a function, :func:`evaluate` is ``mira eval``;
``mira.load_policy`` (:mod:`mira.agents.policy_file`) gives a trained policy's ``predict``.

::

    import mira

    run = mira.train(task="hopper", method="dense", steps=30_000, seed=0, out="runs/hopper-api")
    policy = mira.load_policy(run.path)          # RUN_DIR/policy.pt; best=True: policy_best.pt
    action = policy.predict(obs)                 # in the environment's own action space
    print(mira.evaluate(policy, episodes=5).summary())

Keyword arguments are ``mira train``'s flags (``learning_starts=`` for ``--learning-starts``, a tuple
for ``hidden=``, ``True`` for a switch such as ``overwrite=``), and ``set={"mira.mcm.delta_t": 1000}``
stands for ``--set mira.mcm.delta_t=1000``; they are checked as the command line checks them, and bad
input raises :class:`~mira.errors.UsageError`. The run directory is the same as the command's.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from mira.agents.policy_file import Policy, load_policy
from mira.cli_types import Parser
from mira.errors import Interrupted, MiraError, UsageError
from mira.loop.playback import PlaybackResult, evaluate_policy
from mira.runio.csvlog import read_csv


class _ApiParser(Parser):
    def error(self, message: str) -> NoReturn:
        raise UsageError(f"mira.train: {message}")


@dataclass(frozen=True)
class TrainedRun:
    """What :func:`train` leaves: the run directory and how the run ended."""

    path: Path
    status: str
    """``finished`` (or ``failed`` when the run stopped on a non-finite loss or a full disk)."""
    step: int
    final_return: float | None
    """The mean return of the run's last evaluation (``eval.csv``), None before any."""

    def load_policy(self, best: bool = False) -> Policy:
        """The run's ``policy.pt`` (``policy_best.pt`` with ``best``)."""
        return load_policy(self.path, best=best)


def _argv(options: Mapping[str, Any], overrides: Mapping[str, Any] | None, known: set[str]) -> list[str]:
    argv: list[str] = []
    for name, value in options.items():
        if value is None or value is False:
            continue
        if name not in known:
            raise UsageError(f"mira.train: no option {name!r} (the options are mira train's flags: "
                             f"{', '.join(sorted(known))}, and set=)")
        flag = "--" + name.replace("_", "-")
        if value is True:
            argv.append(flag)
        elif isinstance(value, list | tuple):
            argv += [flag, ",".join(str(v) for v in value)]
        else:
            argv += [flag, str(value)]
    for key, value in (overrides or {}).items():
        argv += ["--set", f"{key}={value if isinstance(value, str) else json.dumps(value)}"]
    return argv


def train(task: str | None = None, method: str | None = None, algo: str | None = None, steps: int | None = None,
          seed: int | None = None, out: str | os.PathLike[str] | None = None, *,
          set: Mapping[str, Any] | None = None, quiet: bool = True, **flags: Any) -> TrainedRun:
    """Train one run, as ``mira train`` does, and return its :class:`TrainedRun`.

    ``resume=DIR`` continues a run (``steps=`` then extends its budget), ``overwrite=True`` replaces a
    non-empty ``out``; any other ``mira train`` flag is a keyword argument of the same name. SIGINT
    (Ctrl-C) and SIGTERM stop the run after its current step with a checkpoint and raise
    :class:`~mira.errors.Interrupted` (a ``KeyboardInterrupt``). A run that fails raises its error; one
    stopped by a non-finite loss or a full disk raises :class:`~mira.errors.MiraError` (it can be resumed).
    PyTorch's thread count is set for the run (``threads``, default 1) and restored afterwards.
    """
    import torch

    from mira.cli import cmd_train
    from mira.train_cli import add_train_arguments

    parser = _ApiParser(prog="mira.train")
    add_train_arguments(parser)
    known = {a.dest for a in parser._actions if a.dest not in ("help", "overrides")}
    options = {"task": task, "method": method, "algo": algo, "steps": steps, "seed": seed,
               "out": None if out is None else os.fspath(out), "quiet": quiet, **flags}
    args = parser.parse_args(_argv(options, set, known))
    threads = torch.get_num_threads()
    try:
        code = cmd_train(args)
    finally:
        torch.set_num_threads(threads)
    path = Path(args.resume or args.out)
    status = _read_status(path)
    if code >= 128:
        raise Interrupted(code - 128, status.get("step"), checkpointed=True)
    if code != 0:
        raise MiraError(f"mira.train: the run in {path} stopped at step {status.get('step')}: "
                        f"{status.get('message') or f'exit status {code}'}; resume it with resume={str(path)!r}")
    evals = read_csv(path / "eval.csv")
    final = float(evals[-1]["return_mean"]) if evals else None
    return TrainedRun(path, str(status.get("status", "unknown")), int(status.get("step", 0)), final)


def _read_status(path: Path) -> dict[str, Any]:
    try:
        data = json.loads((path / "status.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def evaluate(policy: Policy | str | os.PathLike[str], episodes: int | None = None, seed: int | None = None,
             video_dir: str | os.PathLike[str] | None = None, best: bool = False) -> PlaybackResult:
    """``mira eval``: play a policy (a :class:`Policy`, a policy file or a run directory) for ``episodes``
    deterministic episodes, from the run's evaluation seeds unless ``seed`` is given, recording an MP4
    per episode in ``video_dir``; ``.mean``, ``.std``, ``.returns``, ``.videos``, ``.summary()``."""
    if not isinstance(policy, Policy):
        policy = load_policy(policy, best=best)
    return evaluate_policy(policy, episodes=episodes, seed=seed, video_dir=video_dir)


__all__ = ["Interrupted", "PlaybackResult", "Policy", "TrainedRun", "evaluate", "load_policy", "train"]
