"""Exception types shared across MIRA.

``UsageError`` marks bad input from a user (flag, task card, program file, sweep file): the command
line prints its message on one line and exits with status 2, without a traceback.
"""

from __future__ import annotations


class MiraError(Exception):
    """Base class of every error MIRA raises on purpose."""


class UsageError(MiraError):
    """Bad input from the user; reported as one line with exit status 2."""


class TaskCardError(UsageError):
    """A task card is malformed, names an unknown environment or an index outside the observation."""


class CheckpointError(MiraError):
    """A checkpoint is missing, truncated or fails its content hash."""


class DiskFullError(MiraError):
    """Writing run state failed for lack of space; the run stops with its last complete state intact."""


class NonFiniteError(MiraError):
    """A loss or the potential became NaN/Inf; the run stops with its last checkpoint intact."""


class Interrupted(KeyboardInterrupt):
    """A run stopped on a signal (SIGINT: Ctrl-C, or SIGTERM); ``signum`` says which. A run that could
    finish its step first has checkpointed it (``checkpointed``), so ``--resume`` continues from there."""

    def __init__(self, signum: int, step: int | None = None, checkpointed: bool = False) -> None:
        super().__init__(signum)
        self.signum = signum
        self.step = step
        self.checkpointed = checkpointed
