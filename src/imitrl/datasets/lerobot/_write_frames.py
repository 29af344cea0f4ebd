"""The frames of a v3.0 dataset, written a slice of whole episodes at a time.

:func:`save_lerobot` reads its rows (in memory, or a disk buffer's memory-mapped files)
in slices of about :data:`SLICE_BYTES` holding whole episodes: each slice becomes one
arrow table, written to the data files, and its episodes' statistics are computed in one
vectorised pass per feature (:func:`~imitrl.datasets.lerobot._stats.segment_stats`),
appended to the episode table (:class:`~imitrl.datasets.lerobot._episode_table.EpisodeTable`)
and added to the running totals of ``meta/stats.json``
(:class:`~imitrl.datasets.lerobot._stats_totals.DatasetStats`); then the slice's pages of
a memory-mapped source are let go (:func:`~imitrl.data.disk.release_pages`). What stays
in memory: one slice, and a few integers per episode (:class:`Episodes`), whatever the
number of frames. A row group holds whole episodes: those of one slice that go to one
file (lerobot 0.4 writes one row group per episode; at about 1 ms per row group, whatever
its size, that alone took 5 s for 1M CartPole frames; readers, LeRobot's included, do not
depend on row groups). Camera frames written as video are read by
:mod:`~imitrl.datasets.lerobot._video_write` from the rows themselves, one episode at a
time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.data.disk import release_pages
from imitrl.datasets._arrow import (
    encode_images,
    hf_feature,
    hf_schema_metadata,
    release_unused_memory,
    tensor_to_array,
)
from imitrl.datasets.lerobot._episode_table import EpisodeTable
from imitrl.datasets.lerobot._layout import DATA_PATH
from imitrl.datasets.lerobot._stats import image_stats, sample_frames, segment_stats
from imitrl.datasets.lerobot._stats_totals import DatasetStats
from imitrl.datasets.lerobot._video_write import next_file
from imitrl.datasets.lerobot._write_plan import Episodes, Plan

SLICE_BYTES = 8 << 20
"""bytes of rows read and converted at once (rounded to whole episodes, at least one); a
row group holds at most one slice, so a streamed load reads at most this much at once"""


def pixels_of(value: Any, layout: Literal["hwc", "chw"]) -> np.ndarray:
    """uint8 ``[N, H, W, 3]`` frames of an image key (a view)."""
    pixels = value.numpy()
    return pixels if layout == "hwc" else pixels.transpose(0, 2, 3, 1)


def slices(episodes: Episodes, row_bytes: int) -> list[tuple[int, int]]:
    """``(first episode, end episode)`` of each slice: whole episodes, about
    :data:`SLICE_BYTES` of rows each (one episode at least)."""
    budget = max(1, SLICE_BYTES // max(1, row_bytes))
    out, first, rows = [], 0, 0
    for e, n in enumerate(episodes.lengths.tolist()):
        if rows and rows + n > budget:
            out.append((first, e))
            first, rows = e, 0
        rows += n
    out.append((first, len(episodes.lengths)))
    return out


def _slice_table(
    plan: Plan, part: TensorDictBase, first_row: int, first_ep: int, lengths: np.ndarray, fps: int
) -> tuple[pa.Table, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """One slice of rows as the data files' table, the values each array feature's
    statistics read, and the ``[n, C, H, W]`` frames of each image and video feature."""
    n = part.shape[0]
    frame_index = part.get(keys.STEP).numpy().astype(np.int64)
    columns: dict[str, pa.Array] = {}
    arrays: dict[str, np.ndarray] = {}
    images: dict[str, np.ndarray] = {}
    for col in plan.columns:
        value = part.get(col.key)
        if col.kind == "video":
            assert col.layout is not None  # an image or video column has one (_write._plan)
            images[col.name] = pixels_of(value, col.layout).transpose(0, 3, 1, 2)
        elif col.kind == "image":
            assert col.layout is not None
            pixels = pixels_of(value, col.layout)
            columns[col.name] = encode_images(pixels, frame_index)
            images[col.name] = pixels.transpose(0, 3, 1, 2)  # (C, H, W), as LeRobot reads them
        else:
            columns[col.name], shape = tensor_to_array(value)
            values = value.numpy()
            arrays[col.name] = values.reshape(n, *shape) if shape != (1,) else values.reshape(n)
    task = part.get("task_index") if "task_index" in part.keys() else None
    book = {
        "timestamp": (frame_index / fps).astype(np.float32),
        "frame_index": frame_index,
        "episode_index": np.repeat(np.arange(first_ep, first_ep + len(lengths)), lengths),
        "index": np.arange(first_row, first_row + n, dtype=np.int64),
        "task_index": (
            np.zeros(n, dtype=np.int64)
            if task is None
            else task.numpy().reshape(n).astype(np.int64)
        ),
    }
    for name, values in book.items():
        columns[name] = pa.array(values)
        arrays[name] = values
    hf = {
        name: hf_feature(plan.info[name]["dtype"], tuple(plan.info[name]["shape"]))
        for name in columns
    }
    table = pa.table(columns).replace_schema_metadata(hf_schema_metadata(hf))
    return table, arrays, images


def _slice_stats(
    arrays: dict[str, np.ndarray], images: dict[str, np.ndarray], lengths: np.ndarray
) -> dict[str, dict[str, np.ndarray]]:
    """feature -> stat -> ``[E_slice, ...]``: LeRobot's ``compute_episode_stats`` of every
    episode of the slice (image features: of their sampled frames, episode by episode)."""
    out = segment_stats(arrays, lengths)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    for name, chw in images.items():
        per = [image_stats(sample_frames(chw[s : s + n])) for s, n in zip(starts, lengths)]
        out[name] = {stat: np.stack([p[stat] for p in per]) for stat in per[0]}
    return out


def write_frames(
    root: Path,
    rows: TensorDictBase,
    plan: Plan,
    episodes: Episodes,
    *,
    table: EpisodeTable,
    totals: DatasetStats,
    fps: int,
    episodes_per_file: int,
    chunks_size: int,
) -> None:
    """The data files under ``root``, ``episodes_per_file`` episodes each (then the next
    file, ``chunks_size`` files per chunk), row groups of whole episodes, read from ``rows``
    a slice at a time; each slice's episodes, with their statistics, appended to ``table``
    and added to ``totals``."""
    row_bytes = sum(v[0].nbytes for v in rows.values(include_nested=True, leaves_only=True))
    chunk, file = 0, 0
    writer: pq.ParquetWriter | None = None
    try:
        for first, end in slices(episodes, row_bytes):
            begin = int(episodes.starts[first])
            lengths = episodes.lengths[first:end]
            part = rows[begin : begin + int(lengths.sum())].cpu()
            data, arrays, images = _slice_table(plan, part, begin, first, lengths, fps)
            places: list[tuple[int, int]] = []
            e, offset = first, 0
            while e < end:  # one row group: the slice's episodes that go to one file
                if e and e % episodes_per_file == 0:  # lerobot's update_chunk_file_indices
                    assert writer is not None  # opened at episode 0, in the first slice
                    writer.close()
                    writer = None
                    chunk, file = next_file(chunk, file, chunks_size)
                if writer is None:
                    path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
                    path.parent.mkdir(parents=True, exist_ok=True)
                    writer = pq.ParquetWriter(
                        path, data.schema, compression="snappy", use_dictionary=True
                    )
                stop = min(end, (e // episodes_per_file + 1) * episodes_per_file)
                n = int(lengths[e - first : stop - first].sum())
                writer.write_table(data.slice(offset, n), row_group_size=n)
                places.extend([(chunk, file)] * (stop - e))
                e, offset = stop, offset + n
            stats = _slice_stats(arrays, images, lengths)
            table.write(first, end, places, stats)
            totals.add({n: stats[n] for n in plan.info if n in stats})  # stats.json's order
            del data, arrays, images
            release_pages(part)  # a memory-mapped source's pages, once read
            release_unused_memory()
    finally:
        if writer is not None:
            writer.close()
