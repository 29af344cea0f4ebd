"""The files of a LeRobot v3.0 dataset, written from rows already checked.

``data/chunk-*/file-*.parquet`` (row groups of whole episodes), the episode table
``meta/episodes/chunk-000/file-000.parquet`` with each episode's statistics
(:mod:`~imitrl.datasets.lerobot._episode_table`; both a slice of episodes at a time),
``meta/tasks.parquet``, ``meta/stats.json``, ``meta/info.json``, the cameras' videos
(:mod:`~imitrl.datasets.lerobot._video_write`) and imitrl's own ``meta/imitrl.json`` (each
column's buffer key and exact shape, each other file's size and SHA-256, videos included,
the entries of ``info.json`` LeRobot keeps when it edits the dataset, and the SHA-256 of its
own content), laid out as lerobot 0.4 writes them.
"""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
from tensordict import TensorDictBase

from imitrl.datasets.lerobot._checks import INFO_TOTALS, file_digest, sidecar_digest
from imitrl.datasets.lerobot._episode_table import EpisodeTable, add_spread
from imitrl.datasets.lerobot._layout import (
    CODEBASE_VERSION,
    DATA_PATH,
    DEFAULT_DATA_FILE_SIZE_IN_MB,
    EPISODES_PATH,
    SIDECAR,
    SIDECAR_FORMAT,
)
from imitrl.datasets.lerobot._stats_totals import DatasetStats
from imitrl.datasets.lerobot._video_write import VIDEO_PATH, VideoFiles, write_videos
from imitrl.datasets.lerobot._write_frames import write_frames
from imitrl.datasets.lerobot._write_plan import Episodes, Plan


def write_v3(
    root: Path,
    rows: TensorDictBase,
    plan: Plan,
    episodes: Episodes,
    *,
    fps: int,
    robot_type: str | None,
    episodes_per_file: int,
    chunks_size: int,
    video_files_size_in_mb: float,
) -> None:
    """Every file of a v3.0 dataset under ``root``: videos (first: the episode table
    records where each episode's frames lie in them), data and episode table a slice at a
    time, tasks, stats, ``info.json`` and ``meta/imitrl.json``."""
    videos = VideoFiles([], {})
    if plan.videos:
        videos = write_videos(
            root,
            plan.videos,
            episodes.starts.tolist(),
            episodes.lengths.tolist(),
            fps=fps,
            chunks_size=chunks_size,
            file_size_in_mb=video_files_size_in_mb,
        )
    totals = DatasetStats(len(episodes.starts))
    ep_path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    with EpisodeTable(ep_path, plan, episodes, videos.episode_columns) as table:
        write_frames(
            root,
            rows,
            plan,
            episodes,
            table=table,
            totals=totals,
            fps=fps,
            episodes_per_file=episodes_per_file,
            chunks_size=chunks_size,
        )
    add_spread(ep_path, totals)  # the pooled variance needs the dataset's means first
    _write_tasks(root, episodes.task_list)
    _write_stats(root, totals)
    n_eps = len(episodes.starts)
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": n_eps,
        "total_frames": int(episodes.lengths.sum()),
        "total_tasks": len(episodes.task_list),
        "chunks_size": chunks_size,
        "data_files_size_in_mb": DEFAULT_DATA_FILE_SIZE_IN_MB,
        "video_files_size_in_mb": video_files_size_in_mb,
        "fps": fps,
        "splits": {"train": f"0:{n_eps}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if plan.videos else None,
        "features": {  # a video feature with the info LeRobot probes from its first file
            name: {**ft, "info": videos.info[name]} if name in videos.info else ft
            for name, ft in plan.info.items()
        },
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    files = {  # every other file's size and SHA-256 (videos too): a changed byte is refused
        f.relative_to(root).as_posix(): file_digest(f)
        for f in sorted(root.rglob("*"))
        if f.is_file()
    }
    kept = {k: v for k, v in info.items() if k not in INFO_TOTALS}  # what LeRobot keeps
    sidecar = {"format": SIDECAR_FORMAT, "columns": plan.sidecar, "files": files, "info": kept}
    sidecar["digest"] = sidecar_digest(sidecar)
    (root / SIDECAR).write_text(json.dumps(sidecar, indent=2))


def _write_tasks(root: Path, task_list: list[str]) -> None:
    """``meta/tasks.parquet``: the task strings as the pandas index, ``task_index`` beside."""
    tasks_table = pa.table(
        {
            "task_index": pa.array(range(len(task_list)), pa.int64()),
            "__index_level_0__": pa.array(task_list, pa.large_string()),
        }
    ).replace_schema_metadata({b"pandas": _pandas_index_metadata()})
    pq.write_table(tasks_table, root / "meta" / "tasks.parquet")


def _write_stats(root: Path, totals: DatasetStats) -> None:
    """``meta/stats.json``: every feature's statistics over the whole dataset, the episodes'
    aggregated as LeRobot aggregates them (:class:`DatasetStats`), features in
    ``info.json``'s order."""
    stats = {
        name: {k: v.tolist() for k, v in totals.result(name).items()} for name in totals.names()
    }
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))


def _pandas_index_metadata() -> bytes:
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
