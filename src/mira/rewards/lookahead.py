"""An optional capability of a reward source: relabelling several upcoming batches at once.

A source whose reward stays one fixed function over several agent updates (HARS between two of its
training steps) can relabel the batches of those updates together, in one pass, and may compute them
on another thread while the agent updates. The trainer then samples :meth:`LookaheadSource.lookahead`
batches at once, relabels them with :meth:`LookaheadSource.relabel_many`, uses them one per update,
and drops any it has not used when :attr:`LookaheadSource.revision` changes (the function changed: a
new program, loaded state, a refit). Sources without it are relabelled one batch at a time.
"""

from __future__ import annotations

from concurrent.futures import Future
from typing import TypeAlias

import torch

from mira.replay import Batch
from mira.rewards.base import RewardSource

Relabelled: TypeAlias = "torch.Tensor | Future[torch.Tensor]"
"""A relabelled reward from :meth:`LookaheadSource.relabel_many`: the tensor, or the Future of a
computation running beside the agent (wait for it with :func:`resolve` when the batch's turn comes)."""


def resolve(reward: Relabelled) -> torch.Tensor:
    """The tensor of a :data:`Relabelled` reward, waiting for it if it is still being computed."""
    return reward.result() if isinstance(reward, Future) else reward


class LookaheadSource(RewardSource):
    """A reward source that may relabel the batches of several upcoming updates in one go."""

    def lookahead(self) -> int:
        """How many upcoming updates' batches :meth:`relabel_many` may relabel now (1: only the next)."""
        return 1

    def relabel_many(self, batches: list[Batch]) -> list[Relabelled]:
        """``[relabel(b) for b in batches]``, for at most :meth:`lookahead` batches (sources may batch it)."""
        return [self.relabel(b) for b in batches]

    @property
    def revision(self) -> int:
        """Changes whenever rewards relabelled earlier (and not yet used) would no longer be current."""
        return 0
