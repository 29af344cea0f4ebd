"""Demonstration data: the growing buffer and whole-episode rollouts."""

from imitrl.data.buffer import REQUIRED_KEYS, DemonstrationBuffer, GrowingTensorStorage
from imitrl.data.rollout import EpisodeSummary, episode_returns, rollout_episodes

__all__ = [
    "REQUIRED_KEYS",
    "DemonstrationBuffer",
    "EpisodeSummary",
    "GrowingTensorStorage",
    "episode_returns",
    "rollout_episodes",
]
