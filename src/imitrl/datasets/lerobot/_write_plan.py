"""What a v3.0 write plans before its first frame: the episodes (a few integers each) and
each feature's column (:func:`~imitrl.datasets.lerobot.save_lerobot`), read by the frame
writer (:mod:`~imitrl.datasets.lerobot._write_frames`) and the episode table
(:mod:`~imitrl.datasets.lerobot._episode_table`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.datasets._common import NestedKey, key_name
from imitrl.datasets.lerobot._checks import TOLERANCE_S


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


def check_timestamps(longest: int, fps: int) -> None:
    """ValueError unless the float32 timestamps of an episode of ``longest`` frames pass
    LeRobot's check (consecutive frames ``1/fps`` apart within its ``tolerance_s``): past
    about 2**10 s float32 is too coarse for it, and lerobot, as ``load_lerobot``, would
    refuse the file."""
    ts = (np.arange(longest) / fps).astype(np.float32).astype(np.float64)
    off = np.flatnonzero(np.abs(np.diff(ts) - 1 / fps) > TOLERANCE_S)
    if off.size:
        most = int(off[0]) + 1
        raise ValueError(
            f"an episode of {longest} frames at fps {fps}: LeRobot stores timestamps as "
            f"float32, too coarse past frame {most} ({most / fps:.0f} s) for its "
            f"{TOLERANCE_S} s check (lerobot and load_lerobot would refuse the file); "
            f"split the episodes into parts of at most {most} frames"
        )


def check_finite_rows(rows: TensorDictBase, chunk: int = 1 << 18) -> None:
    """ValueError naming the key, episode and step of the first NaN or inf among the
    rows' floating values (``load_lerobot`` refuses them: they would poison training),
    read ``chunk`` rows at a time."""
    for key in rows.keys(include_nested=True, leaves_only=True):
        values = rows.get(key)
        if not values.is_floating_point():
            continue
        for start in range(0, rows.shape[0], chunk):
            part = values[start : start + chunk]
            bad = ~torch.isfinite(part.reshape(part.shape[0], -1)).all(-1)
            if bool(bad.any()):
                i = start + int(torch.nonzero(bad)[0, 0])
                episode, step = int(rows.get(keys.EPISODE)[i]), int(rows.get(keys.STEP)[i])
                raise ValueError(
                    f"rows' {key_name(key)!r} at episode {episode}, step {step} holds NaN or "
                    "inf: a LeRobot dataset of it could not be loaded (NaN and inf are refused)"
                )
