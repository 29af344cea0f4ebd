"""The files of a LeRobot v3.0 dataset, written from features already checked.

``data/chunk-*/file-*.parquet`` (one row group per episode), the episode table
``meta/episodes/chunk-000/file-000.parquet`` with each episode's statistics,
``meta/tasks.parquet``, ``meta/stats.json``, ``meta/info.json``, the cameras' videos
(:mod:`~imitrl.datasets.lerobot._video_write`) and imitrl's own ``meta/imitrl.json`` (each
column's buffer key and exact shape, each other file's size and SHA-256, videos included,
and the SHA-256 of its own content), laid out as lerobot 0.4 writes them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from imitrl.datasets._arrow import hf_feature, hf_schema_metadata
from imitrl.datasets.lerobot._checks import file_digest, sidecar_digest
from imitrl.datasets.lerobot._layout import (
    CODEBASE_VERSION,
    DATA_PATH,
    DEFAULT_DATA_FILE_SIZE_IN_MB,
    EPISODES_PATH,
    SIDECAR,
    SIDECAR_FORMAT,
)
from imitrl.datasets.lerobot._stats import (
    aggregate_stats,
    feature_stats,
    image_stats,
    sample_frames,
)
from imitrl.datasets.lerobot._video_write import VIDEO_PATH, VideoFiles, next_file, write_videos


@dataclass(frozen=True)
class Episodes:
    """The episodes written: contiguous blocks of the ``N`` frames, and their tasks."""

    starts: list[int]
    """first frame of each episode"""
    lengths: list[int]
    """frames of each episode"""
    task_index: torch.Tensor
    """``[N]`` each frame's index into ``tasks``"""
    tasks: list[str]
    """the task strings"""


@dataclass(frozen=True)
class Features:
    """What :func:`save_lerobot` writes, feature by feature, in column order."""

    columns: dict[str, pa.Array]
    """feature -> ``[N]`` arrow column of the data files"""
    info: dict[str, dict]
    """feature -> its ``info.json`` entry (dtype, shape, names)"""
    sidecar: dict[str, dict]
    """feature -> its ``meta/imitrl.json`` entry (buffer key, exact per-frame shape)"""
    arrays: dict[str, np.ndarray]
    """feature -> ``[N, ...]`` values for :func:`feature_stats`"""
    images: dict[str, np.ndarray]
    """image and video feature -> ``[N, C, H, W]`` frames for :func:`image_stats`"""
    videos: dict[str, np.ndarray] = field(default_factory=dict)
    """video feature -> uint8 ``[N, H, W, 3]`` frames to encode (no column in the data files)"""

    def table(self) -> pa.Table:
        """The frames as one table, with the Hugging Face ``datasets`` schema metadata (of the
        columns only: video features live in ``videos/``, as LeRobot's ``get_hf_features``
        leaves them out)."""
        hf = {
            name: hf_feature(self.info[name]["dtype"], tuple(self.info[name]["shape"]))
            for name in self.columns
        }
        return pa.table(self.columns).replace_schema_metadata(hf_schema_metadata(hf))


def write_v3(
    root: Path,
    table: pa.Table,
    features: Features,
    episodes: Episodes,
    *,
    fps: int,
    robot_type: str | None,
    episodes_per_file: int,
    chunks_size: int,
    video_files_size_in_mb: float,
) -> None:
    """Every file of a v3.0 dataset under ``root``: data, videos, episode table, tasks,
    stats, ``info.json`` and ``meta/imitrl.json``."""
    places = _write_data(root, table, episodes, episodes_per_file, chunks_size)
    videos = VideoFiles([{} for _ in episodes.starts], {})
    if features.videos:
        videos = write_videos(
            root,
            features.videos,
            episodes.starts,
            episodes.lengths,
            fps=fps,
            chunks_size=chunks_size,
            file_size_in_mb=video_files_size_in_mb,
        )
    ep_stats = _episode_stats(features, episodes)
    ep_rows = _episode_rows(features, episodes, places, videos.episode_columns, ep_stats)
    ep_path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    ep_path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(ep_rows), ep_path, compression="snappy")
    _write_tasks(root, episodes.tasks)
    _write_stats(root, features, ep_stats)
    n_eps = len(episodes.starts)
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": n_eps,
        "total_frames": int(sum(episodes.lengths)),
        "total_tasks": len(episodes.tasks),
        "chunks_size": chunks_size,
        "data_files_size_in_mb": DEFAULT_DATA_FILE_SIZE_IN_MB,
        "video_files_size_in_mb": video_files_size_in_mb,
        "fps": fps,
        "splits": {"train": f"0:{n_eps}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if features.videos else None,
        "features": {  # a video feature with the info LeRobot probes from its first file
            name: {**ft, "info": videos.info[name]} if name in videos.info else ft
            for name, ft in features.info.items()
        },
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    files = {  # every other file's size and SHA-256 (videos too): a changed byte is refused
        f.relative_to(root).as_posix(): file_digest(f)
        for f in sorted(root.rglob("*"))
        if f.is_file()
    }
    sidecar = {"format": SIDECAR_FORMAT, "columns": features.sidecar, "files": files}
    sidecar["digest"] = sidecar_digest(sidecar)
    (root / SIDECAR).write_text(json.dumps(sidecar, indent=2))


def _write_data(
    root: Path,
    table: pa.Table,
    episodes: Episodes,
    episodes_per_file: int,
    chunks_size: int,
) -> list[tuple[int, int]]:
    """The data files, ``episodes_per_file`` episodes each, one row group per episode;
    returns each episode's ``(chunk_index, file_index)``."""
    places: list[tuple[int, int]] = []
    chunk, file = 0, 0
    writer: pq.ParquetWriter | None = None
    for i, (s, n) in enumerate(zip(episodes.starts, episodes.lengths)):
        if i and i % episodes_per_file == 0:  # next file (lerobot's update_chunk_file_indices)
            writer.close()
            writer = None
            chunk, file = next_file(chunk, file, chunks_size)
        if writer is None:
            data_path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
            data_path.parent.mkdir(parents=True, exist_ok=True)
            writer = pq.ParquetWriter(
                data_path, table.schema, compression="snappy", use_dictionary=True
            )
        writer.write_table(table.slice(s, n))  # one row group per episode, as lerobot writes
        places.append((chunk, file))
    assert writer is not None
    writer.close()
    return places


def _episode_rows(
    features: Features,
    episodes: Episodes,
    places: list[tuple[int, int]],
    video_columns: list[dict[str, Any]],
    ep_stats: list[dict[str, dict[str, np.ndarray]]],
) -> list[dict[str, Any]]:
    """One row of the episode table per episode: tasks, length, data file, frame range,
    each camera's video file and time span, and its ``stats/<feature>/<stat>``, in the
    order LeRobot's ``save_episode`` writes them."""
    ep_rows: list[dict[str, Any]] = []
    for i, (s, n) in enumerate(zip(episodes.starts, episodes.lengths)):
        chunk, file = places[i]
        frame_tasks = episodes.task_index[s : s + n].tolist()
        row: dict[str, Any] = {
            "episode_index": i,
            "tasks": sorted({episodes.tasks[t] for t in frame_tasks}),
            "length": n,
            "data/chunk_index": chunk,
            "data/file_index": file,
            "dataset_from_index": s,
            "dataset_to_index": s + n,
            **video_columns[i],
        }
        for name in features.info:  # in feature order, as LeRobot writes the columns
            for stat, v in ep_stats[i].get(name, {}).items():
                row[f"stats/{name}/{stat}"] = v.tolist()
        row["meta/episodes/chunk_index"] = 0
        row["meta/episodes/file_index"] = 0
        ep_rows.append(row)
    return ep_rows


def _write_tasks(root: Path, task_list: list[str]) -> None:
    """``meta/tasks.parquet``: the task strings as the pandas index, ``task_index`` beside."""
    tasks_table = pa.table(
        {
            "task_index": pa.array(range(len(task_list)), pa.int64()),
            "__index_level_0__": pa.array(task_list, pa.large_string()),
        }
    ).replace_schema_metadata({b"pandas": _pandas_index_metadata(len(task_list))})
    pq.write_table(tasks_table, root / "meta" / "tasks.parquet")


def _episode_stats(features: Features, episodes: Episodes) -> list[dict[str, dict]]:
    """Each episode's statistics of every feature (images and videos: of its sampled
    frames), as LeRobot's ``compute_episode_stats`` computes them."""
    out = []
    for s, n in zip(episodes.starts, episodes.lengths):
        stats = {name: feature_stats(values[s : s + n]) for name, values in features.arrays.items()}
        for name, chw in features.images.items():
            stats[name] = image_stats(sample_frames(chw[s : s + n]))
        out.append(stats)
    return out


def _write_stats(root: Path, features: Features, ep_stats: list[dict[str, dict]]) -> None:
    """``meta/stats.json``: every feature's statistics over the whole dataset, the episodes'
    aggregated as LeRobot aggregates them (:func:`aggregate_stats`; memory of one episode's
    frames, not the dataset's)."""
    stats = {
        name: {k: v.tolist() for k, v in aggregate_stats([e[name] for e in ep_stats]).items()}
        for name in features.info
        if name in ep_stats[0]
    }
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))


def _pandas_index_metadata(n_rows: int) -> bytes:
    """The pandas metadata ``DataFrame.to_parquet`` writes, so ``pd.read_parquet`` restores
    the task strings as the index (LeRobot looks tasks up with ``tasks.loc[task]``)."""
    return json.dumps(
        {
            "index_columns": ["__index_level_0__"],
            "column_indexes": [
                {
                    "name": None,
                    "field_name": None,
                    "pandas_type": "unicode",
                    "numpy_type": "object",
                    "metadata": {"encoding": "UTF-8"},
                }
            ],
            "columns": [
                {
                    "name": "task_index",
                    "field_name": "task_index",
                    "pandas_type": "int64",
                    "numpy_type": "int64",
                    "metadata": None,
                },
                {
                    "name": None,
                    "field_name": "__index_level_0__",
                    "pandas_type": "unicode",
                    "numpy_type": "object",
                    "metadata": None,
                },
            ],
            "creator": {"library": "pyarrow", "version": pa.__version__},
            "pandas_version": "2.2.0",
        }
    ).encode()
