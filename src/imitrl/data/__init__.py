"""Demonstration data: the growing buffer (in memory or on disk) and whole-episode rollouts."""

from imitrl.data.buffer import (
    OBSERVATION_KEYS,
    REQUIRED_KEYS,
    DemonstrationBuffer,
    GrowingTensorStorage,
)
from imitrl.data.returns import EpisodeSummary, episode_returns
from imitrl.data.rollout import rollout_episodes

__all__ = [
    "OBSERVATION_KEYS",
    "REQUIRED_KEYS",
    "DemonstrationBuffer",
    "EpisodeSummary",
    "GrowingTensorStorage",
    "episode_returns",
    "rollout_episodes",
]
