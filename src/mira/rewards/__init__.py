"""Reward sources: the pluggable part of the one trainer."""

from mira.rewards.base import DenseReward, RewardContext, RewardSource, SparseReward

__all__ = ["DenseReward", "RewardContext", "RewardSource", "SparseReward"]
