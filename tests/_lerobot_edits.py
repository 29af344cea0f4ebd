"""LeRobot's in-place edits of a dataset, file for file, without the lerobot package.

What lerobot 0.6.1 does to a dataset folder (``src/lerobot/datasets/dataset_writer.py``,
``dataset_metadata.py``, ``dataset_tools.py``):

* ``LeRobotDataset.resume(repo_id, root)`` then ``save_episode()``: the new episodes'
  frames go to the *next* data file (``update_chunk_file_indices`` after the last episode's
  ``data/chunk_index, data/file_index``), their rows to the next episode-table file, with
  ``dataset_from_index`` continuing the frame count; ``meta/info.json`` is written again
  by ``write_info(DatasetInfo.to_dict())`` with new ``total_episodes``, ``total_frames``,
  ``total_tasks`` and ``splits`` (``json.dump(indent=4, ensure_ascii=False)``, the
  dataclass's field order), ``meta/stats.json`` with the statistics aggregated over old and
  new episodes, ``meta/tasks.parquet`` only when a task is new. Every other file, and
  ``meta/imitrl.json``, stays as it was.
* ``recompute_stats(dataset)`` (``lerobot-edit-dataset --operation.type recompute_stats``):
  ``meta/stats.json`` only.

The new files are cut out of a dataset :func:`save_lerobot` writes for old + new rows
(its frames, episode rows and statistics are LeRobot's layout and digits).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import torch
from tensordict import TensorDict

from imitrl.datasets import save_lerobot

INFO_ORDER = (
    "codebase_version",
    "fps",
    "features",
    "total_episodes",
    "total_frames",
    "total_tasks",
    "chunks_size",
    "data_files_size_in_mb",
    "video_files_size_in_mb",
    "data_path",
    "video_path",
    "robot_type",
    "splits",
)
"""``DatasetInfo``'s fields, the order ``to_dict`` writes them in (``tools`` dropped when None)"""


def write_info_like_lerobot(root: Path, info: dict) -> None:
    """``write_info(DatasetInfo.from_dict(info), root)``."""
    d = {k: info[k] for k in INFO_ORDER if k in info}
    with open(root / "meta" / "info.json", "w") as f:
        json.dump(d, f, indent=4, ensure_ascii=False)


def resume_like_lerobot(root: Path, before: TensorDict, added: TensorDict, *, fps: int) -> None:
    """Record ``added`` (whole episodes, ``STEP`` 0..length-1) into the dataset at ``root``,
    which :func:`save_lerobot` wrote from ``before`` (one data file, one episode file), as
    ``LeRobotDataset.resume`` + ``save_episode`` do."""
    with tempfile.TemporaryDirectory() as tmp:
        n_before = len(torch.unique(before.get("episode")))
        both = save_lerobot(
            torch.cat([before, added]), Path(tmp) / "both", fps=fps, episodes_per_file=n_before
        )
        shutil.copy(
            both / "data/chunk-000/file-001.parquet", root / "data/chunk-000/file-001.parquet"
        )
        table = pq.read_table(both / "meta/episodes/chunk-000/file-000.parquet")
        new = table.slice(n_before)
        for column, value in (("meta/episodes/chunk_index", 0), ("meta/episodes/file_index", 1)):
            i = new.schema.get_field_index(column)
            new = new.set_column(i, column, pa.array([value] * new.num_rows, pa.int64()))
        pq.write_table(new, root / "meta/episodes/chunk-000/file-001.parquet")
        shutil.copy(both / "meta/stats.json", root / "meta/stats.json")
        info = json.loads((root / "meta/info.json").read_text())
        totals = json.loads((both / "meta/info.json").read_text())
        for field in ("total_episodes", "total_frames", "total_tasks", "splits"):
            info[field] = totals[field]
        write_info_like_lerobot(root, info)


def recompute_stats_like_lerobot(root: Path) -> None:
    """``recompute_stats``: ``meta/stats.json`` written again by ``write_stats`` (here the
    same statistics to 6 significant digits: another pass over the data, other digits)."""
    stats = json.loads((root / "meta/stats.json").read_text())

    def again(value):
        if isinstance(value, list):
            return [again(v) for v in value]
        return float(f"{value:.6g}") if isinstance(value, float) else value

    fresh = {f: {k: again(v) for k, v in s.items()} for f, s in stats.items()}
    with open(root / "meta/stats.json", "w") as f:
        json.dump(fresh, f, indent=4, ensure_ascii=False)
