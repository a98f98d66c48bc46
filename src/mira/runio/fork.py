"""A fork: a new run directory that continues another run's checkpoint under a seed of its own.

Two forks of one checkpoint that differ in one setting (the outer loop on or off, another reward
engineer) are a paired experiment: they share everything learned up to the fork, and with the same seed
they are the same run until the setting first makes a difference. Between machines a seed's result moves
with the CPU's float rounding alone, so pairs on one machine are how an edit's effect is measured.

The fork's directory holds what it needs to run and resume on its own: its ``config.json`` (the parent's
configuration with the fork's changes, and ``forked_from``: the parent, the step and the checkpoint's
SHA-256), a copy of that checkpoint, the parent's program versions up to the one in force at the step,
and the parent's LLM response cache. Its logs start at the fork; the parent's record before the step
stays in the parent. The trainer reseeds every random stream when it starts from the copied checkpoint
(:meth:`mira.loop.trainer.Trainer._restore`).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Any

from mira.errors import CheckpointError, UsageError
from mira.runio.checkpoint import checkpoint_files, list_checkpoints, load_checkpoint

_VERSION_FILE = re.compile(r"v(\d{3,})\.(json|diff)")


def fork_checkpoint(parent: Path, step: int | None) -> tuple[int, dict[str, Any]]:
    """The parent's checkpoint at ``step`` (its newest when None), verified and loaded."""
    steps = list_checkpoints(parent / "checkpoints")
    if not steps:
        raise UsageError(f"--fork {parent}: the run has no checkpoint to continue from")
    if step is None:
        step = steps[-1]
    elif step not in steps:
        raise UsageError(f"--fork {parent} --fork-step {step}: no checkpoint at that step "
                         f"(the run keeps checkpoints at {', '.join(map(str, steps))})")
    try:
        return step, load_checkpoint(parent / "checkpoints", step)
    except CheckpointError as exc:
        raise UsageError(f"--fork {parent}: {exc}") from exc


def program_version_at(state: dict[str, Any]) -> int | None:
    """The version of the factor program in force in a checkpoint (its outer loop's), or None without one."""
    versions = [int(h["program"]["version"]) for h in state.get("hooks", [])
                if isinstance(h, dict) and isinstance(h.get("program"), dict)]
    return max(versions) if versions else None


def copy_fork_files(parent: Path, step: int, out: Path, program_version: int | None) -> None:
    """Into the (empty) run directory ``out``: the checkpoint of ``step``, the program versions up to
    ``program_version`` (all when None) and the LLM response cache."""
    (out / "checkpoints").mkdir(parents=True)
    for src in checkpoint_files(parent / "checkpoints", step):
        shutil.copy2(src, out / "checkpoints" / src.name)
    programs = parent / "programs"
    if programs.is_dir():
        (out / "programs").mkdir()
        for src in programs.iterdir():
            match = _VERSION_FILE.fullmatch(src.name)
            if match and program_version is not None and int(match.group(1)) > program_version:
                continue
            if src.is_file():
                shutil.copy2(src, out / "programs" / src.name)
    cache = parent / "llm" / "cache"
    if cache.is_dir():
        shutil.copytree(cache, out / "llm" / "cache")
