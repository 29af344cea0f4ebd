"""The v3.0 episode table, written a slice of episodes at a time.

``meta/episodes/chunk-000/file-000.parquet`` holds one row per episode: tasks, length,
data file, frame range, each camera's video file and time span, its
``stats/<feature>/<stat>`` and its own place, in the order LeRobot's ``save_episode``
writes the columns. :class:`EpisodeTable` appends the episodes a slice at a time through
a ``pyarrow.parquet.ParquetWriter``, a row group every :data:`ROW_GROUP_BYTES`, so that
what it holds of them is bounded whatever their number. The table read back is the one
``pa.table`` of every episode at once would give (same columns, types and values); the
file is byte for byte what ``pq.write_table`` of that table writes while the episodes
fit in one row group (about 4,500 episodes of 15 features), only its row groups differ
past that. :func:`add_spread` reads the
episodes' mean, std and count back from it, a row group at a time, for the pooled
variance of ``meta/stats.json`` (:class:`~imitrl.datasets.lerobot._stats_totals.DatasetStats`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from imitrl.datasets._arrow import release_unused_memory
from imitrl.datasets.lerobot._stats_totals import DatasetStats
from imitrl.datasets.lerobot._write_plan import Episodes, Plan

ROW_GROUP_BYTES = 8 << 20
"""arrow bytes of episode rows held before they are written as one row group"""


def list_column(values: np.ndarray) -> pa.Array:
    """``[E, *shape]`` -> nested ``list<...>`` column, one entry per episode, of the type
    ``pa.array(values.tolist())`` infers (float -> double, integer -> int64, bool), built
    from the flat values without a Python object per number."""
    kind = {"f": np.float64, "i": np.int64, "u": np.int64, "b": np.bool_}[values.dtype.kind]
    arr: pa.Array = pa.array(values.reshape(-1).astype(kind))
    for size in reversed(values.shape[1:]):
        offsets = pa.array(np.arange(0, len(arr) + 1, size, dtype=np.int32))
        arr = pa.ListArray.from_arrays(offsets, arr)
    return arr


def _list_values(column: pa.ChunkedArray, shape: tuple[int, ...]) -> np.ndarray:
    """A :func:`list_column` read back: ``[E, *shape]``."""
    arr = column.combine_chunks()
    while pa.types.is_list(arr.type):
        arr = arr.flatten()
    return arr.to_numpy(zero_copy_only=False).reshape(len(column), *shape)


class EpisodeTable:
    """The episode table at ``path``, written by :meth:`write` a slice of episodes at a
    time, in episode order; :meth:`close` finishes the file.

    Args:
        path: the table's file.
        plan: the features (their ``stats/...`` columns follow ``plan.info``'s order).
        episodes: every episode's place in the rows and tasks.
        video_columns: per episode, ``videos/<camera>/...`` -> value (empty: no camera).
    """

    def __init__(
        self, path: Path, plan: Plan, episodes: Episodes, video_columns: list[dict[str, Any]]
    ) -> None:
        self.path, self.plan, self.episodes = path, plan, episodes
        self.video_columns = video_columns
        self._writer: pq.ParquetWriter | None = None
        self._pending: list[pa.Table] = []  # rows not written yet, fewer than a row group
        self._pending_bytes = 0

    def write(
        self,
        first: int,
        end: int,
        places: list[tuple[int, int]],
        stats: dict[str, dict[str, np.ndarray]],
    ) -> None:
        """Episodes ``first .. end - 1``: their ``(chunk_index, file_index)`` data files and
        ``feature -> stat -> [end - first, ...]`` statistics."""
        starts = self.episodes.starts[first:end]
        lengths = self.episodes.lengths[first:end]
        columns: dict[str, Any] = {
            "episode_index": np.arange(first, end),
            "tasks": self.episodes.tasks(first, end),
            "length": lengths,
            "data/chunk_index": [c for c, _ in places],
            "data/file_index": [f for _, f in places],
            "dataset_from_index": starts,
            "dataset_to_index": starts + lengths,
        }
        cameras = self.video_columns[first:end]
        for name in cameras[0] if cameras else ():
            columns[name] = [v[name] for v in cameras]
        for name in self.plan.info:  # in feature order, as LeRobot writes the columns
            for stat, values in stats.get(name, {}).items():
                columns[f"stats/{name}/{stat}"] = list_column(values)
        columns["meta/episodes/chunk_index"] = np.zeros(end - first, dtype=np.int64)
        columns["meta/episodes/file_index"] = np.zeros(end - first, dtype=np.int64)
        table = pa.table(
            {k: v if isinstance(v, pa.Array) else pa.array(v) for k, v in columns.items()}
        )
        self._pending.append(table)
        self._pending_bytes += table.nbytes
        if self._pending_bytes >= ROW_GROUP_BYTES:
            self._flush()

    def _flush(self) -> None:
        """The pending rows as one row group (one chunk per column, as ``pa.table`` of
        them at once holds them)."""
        if not self._pending:
            return
        table = pa.concat_tables(self._pending).combine_chunks()
        self._pending, self._pending_bytes = [], 0
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(self.path, table.schema, compression="snappy")
        self._writer.write_table(table, row_group_size=table.num_rows)

    def close(self) -> None:
        """Write what is pending and finish the file."""
        self._flush()
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> EpisodeTable:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is not None:  # a failed save: what is pending is not written
            self._pending, self._pending_bytes = [], 0
        self.close()


def add_spread(path: Path, totals: DatasetStats) -> None:
    """Pass 2 of ``meta/stats.json``: every feature's episode means, stds and counts, read
    back from the episode table at ``path`` a row group at a time, into ``totals``."""
    table = pq.ParquetFile(path, pre_buffer=False)
    names = totals.names()
    shapes = {name: totals.mean(name).shape for name in names}
    columns = [f"stats/{n}/{s}" for n in names for s in ("mean", "std", "count")]
    for group in range(table.num_row_groups):
        part = table.read_row_group(group, columns=columns, use_threads=False)
        totals.add_spread(
            {n: _list_values(part[f"stats/{n}/mean"], shapes[n]) for n in names},
            {n: _list_values(part[f"stats/{n}/std"], shapes[n]) for n in names},
            {n: _list_values(part[f"stats/{n}/count"], (1,)) for n in names},
        )
        del part
        release_unused_memory()
