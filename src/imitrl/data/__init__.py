"""Demonstration data: the growing buffer (in memory or on disk), its checkpoints, and the
labels a row carries beyond its step (action chunks, observation histories)."""

from imitrl.data.buffer import (
    OBSERVATION_KEYS,
    REQUIRED_KEYS,
    DemonstrationBuffer,
    GrowingTensorStorage,
)

__all__ = [
    "OBSERVATION_KEYS",
    "REQUIRED_KEYS",
    "DemonstrationBuffer",
    "GrowingTensorStorage",
]
