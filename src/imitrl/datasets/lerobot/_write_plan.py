"""What a v3.0 write plans before its first frame: the episodes (a few integers each) and
each feature's column (:func:`~imitrl.datasets.lerobot.save_lerobot`), read by the frame
writer (:mod:`~imitrl.datasets.lerobot._write_frames`) and the episode table
(:mod:`~imitrl.datasets.lerobot._episode_table`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from imitrl.datasets._common import NestedKey


@dataclass(frozen=True)
class Episodes:
    """The episodes written: contiguous blocks of the ``N`` rows, and their tasks; a few
    integers per episode."""

    starts: np.ndarray
    """``[E]`` int64: first row of each episode"""
    lengths: np.ndarray
    """``[E]`` int64: rows of each episode"""
    task_pairs: np.ndarray
    """``[P, 2]`` int64: every distinct ``(episode, task_index)`` of the rows, sorted"""
    task_list: list[str]
    """every task string, indexed by ``task_index``"""

    def tasks(self, first: int, end: int) -> list[list[str]]:
        """Episodes ``first .. end - 1``'s task strings, each sorted (the episode table's
        ``tasks``)."""
        lo, hi = np.searchsorted(self.task_pairs[:, 0], [first, end])
        out: list[list[str]] = [[] for _ in range(end - first)]
        for e, t in self.task_pairs[lo:hi].tolist():
            out[e - first].append(self.task_list[t])
        return [sorted(t) for t in out]


@dataclass(frozen=True)
class Column:
    """One key of the rows as a LeRobot feature."""

    key: NestedKey
    name: str
    """the feature name"""
    kind: Literal["array", "image", "video"]
    layout: Literal["hwc", "chw"] | None
    """how an image or video key holds its frames"""


@dataclass(frozen=True)
class Plan:
    """What :func:`save_lerobot` writes, feature by feature, in column order."""

    columns: list[Column]
    """the rows' keys as features (bookkeeping columns aside)"""
    info: dict[str, dict]
    """feature -> its ``info.json`` entry (dtype, shape, names), bookkeeping included"""
    sidecar: dict[str, dict]
    """feature -> its ``meta/imitrl.json`` entry (buffer key, exact per-frame shape)"""
    videos: dict[str, np.ndarray]
    """video feature -> uint8 ``[N, H, W, 3]`` frames to encode (a view of the rows)"""
