"""Diagnostics only: how well a baseline's per-step reward tracks the hidden dense reward.

This module is the **only** place in :mod:`mira.baselines` that reads ``buffer.dense_reward``. Its
result is logged (field ``corr_dense``) and returned to nobody else: no reward, loss or fit of any
baseline depends on it. The test suite checks that by filling the dense column with NaN and with
random numbers and asserting the rewards are finite and unchanged.
"""

from __future__ import annotations

import numpy as np
import torch

from mira.replay import ReplayBuffer


def dense_reward_correlation_for_logging(
    reward: torch.Tensor, buffer: ReplayBuffer, indices: np.ndarray
) -> torch.Tensor:
    """Pearson correlation (0-d tensor) of ``reward`` ``[B]`` with the dense reward at buffer rows ``indices``.

    0 where it is undefined (either side constant on the batch); NaN if the dense column holds NaN.
    Computed without ``.item()``, so it costs no device synchronisation.
    """
    with torch.no_grad():
        dense = buffer.dense_reward[torch.from_numpy(np.asarray(indices))].to(reward.device, torch.float32)
        x = reward.detach().to(torch.float32).reshape(-1)
        x = x - x.mean()
        y = dense - dense.mean()
        denom = torch.sqrt((x * x).sum() * (y * y).sum())
        corr = (x * y).sum() / denom.clamp_min(1e-12)
        return torch.where((denom > 1e-12) | denom.isnan(), corr, torch.zeros_like(corr))
