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
