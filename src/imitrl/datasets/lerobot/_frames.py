"""A LeRobot dataset's frames, read whole and checked against its episode table.

Frames are read file by file; v3.0 files are concatenated in sorted order, as LeRobot
does, and each episode is the slice ``[dataset_from_index, dataset_to_index)`` of that
concatenation (the episode table's file pointers are not needed, and LeRobot's own
aggregate tool leaves them stale: they only name a missing file when frames are
missing too); v2.x has one file per episode. Every file is opened inside the load's
pinned folder (:mod:`~imitrl.datasets.lerobot._files`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import torch

from imitrl import keys
from imitrl.datasets._arrow import column_to_tensor, footer_rows, read_parquet
from imitrl.datasets._common import NestedKey, key_name
from imitrl.datasets.lerobot._checks import check_frames
from imitrl.datasets.lerobot._episodes import LISTED, episode_dicts, episode_table, v3_data_files
from imitrl.datasets.lerobot._files import holds
from imitrl.datasets.lerobot._interventions import feature_values
from imitrl.datasets.lerobot._layout import data_file
from imitrl.fs.reading import OpenedFolder


@dataclass(frozen=True)
class _Frames:
    """Every frame of the data files, back to back in file order (``F`` frames)."""

    columns: dict[str, list[torch.Tensor]]
    """feature -> its values, one ``[F_file, *shape]`` tensor per file"""
    book: dict[str, torch.Tensor]
    """``[F]`` LeRobot's ``episode_index`` and ``frame_index`` columns, and its ``timestamp``
    and ``task_index`` where ``info.json`` declares them"""
    bounds: list[tuple[int, int, Path]]
    """``(first frame, end frame, file)`` of each file"""
    total: int
    """``F``"""

    @property
    def episode_index(self) -> torch.Tensor:
        return self.book["episode_index"]

    @property
    def frame_index(self) -> torch.Tensor:
        return self.book["frame_index"]

    def file_at(self, i: int) -> Path:
        """The file holding frame ``i`` (the last file past the end)."""
        return next((p for s, e, p in self.bounds if s <= i < e), self.bounds[-1][2])


def data_files(
    folder: OpenedFolder,
    info: dict,
    major: int,
    table: pa.Table,
    v3_files: dict[str, int] | None,
) -> tuple[list[str], str]:
    """The data files to read (relative to the folder), in order, and who names them (for
    messages): v3.0's sorted ``data/*/*.parquet`` (``v3_files``:
    :func:`~imitrl.datasets.lerobot._episodes.v3_data_files`; a missing file the episode
    table names is reported when frames are missing), v2.x's one per episode (``table``:
    :func:`~imitrl.datasets.lerobot._episodes.episode_table`).

    v3.0: before any file is read, the frames their footers declare must be the episodes'
    frames, and ``info.json``'s ``total_frames`` (where it has one) too
    (:func:`check_total_frames`): a data file declaring millions of frames more than the
    metadata is refused, not read (v2.x: :func:`footer_frames`)."""
    root = folder.root
    if major != 3:
        named_by = f"meta/info.json's data_path {info['data_path']!r}"
        return [data_file(root, info, major, ep) for ep in episode_dicts(table)], named_by
    files = list(v3_files or {})
    expected = int(table.column("length").to_numpy().sum())
    held = sum((v3_files or {}).values())
    if held < expected:
        places = table.select(["episode_index", "data/chunk_index", "data/file_index"])
        episodes = places.to_pylist()
        named = [data_file(root, info, major, ep) for ep in episodes]
        absent = [f for f in named if not holds(folder, f)]
        if absent:
            eps = [int(ep["episode_index"]) for ep, f in zip(episodes, named) if f == absent[0]]
            raise ValueError(
                f"{root / absent[0]}: file not found (the episode table places episode(s) "
                f"{eps} there; the data files hold {held} of {expected} frames)"
            )
    if not files:
        raise ValueError(f"{root / 'data'}: no data files (data/chunk-*/file-*.parquet)")
    if held != expected:
        raise ValueError(
            f"{root / 'data'}: the data files hold {held:,} frames (their footers say), the "
            f"episode table covers {expected:,}; refused before reading them"
        )
    check_total_frames(root, info, held)
    return files, LISTED


def check_total_frames(root: Path, info: dict, frames: int) -> None:
    """``info.json``'s ``total_frames``, where it has one, is the ``frames`` the data files
    hold."""
    total = info.get("total_frames")
    if total is not None and total != frames:
        raise ValueError(
            f"{root / 'meta' / 'info.json'} declares {total} frames, the data files hold {frames}"
        )


def footer_frames(
    folder: OpenedFolder,
    info: dict,
    major: int,
    files: list[str],
    named_by: str,
    v3_files: dict[str, int] | None,
    episodes: list[dict],
) -> list[int]:
    """The frames each data file holds by its footer, before any is read: v3.0's as
    :func:`data_files` checked them; v2.x's (one file per episode) each its episode's
    length, and together ``info.json``'s ``total_frames``."""
    if major == 3:
        return [(v3_files or {})[f] for f in files]
    rows = [footer_rows(folder, f, named_by=named_by) for f in files]
    for f, n, ep in zip(files, rows, episodes):
        if n != int(ep["length"]):
            raise ValueError(
                f"{folder.root / f}: episode {int(ep['episode_index'])} has {n} frames (its "
                f"footer says), the episode metadata says {int(ep['length'])}; refused before "
                "reading it"
            )
    check_total_frames(folder.root, info, sum(rows))
    return rows


def _read_frames(
    folder: OpenedFolder,
    files: list[str],
    rows: list[int],
    named_by: str,
    plan: Mapping[str, NestedKey],
    features: dict[str, dict],
) -> _Frames:
    """The planned features and the bookkeeping columns of every file, as tensors; each
    file opened inside the folder (``named_by`` names them, for messages) and read once
    its footer declares its ``rows``."""
    book_names = ["episode_index", "frame_index"]
    book_names += [c for c in ("timestamp", "task_index") if c in features]
    columns: dict[str, list[torch.Tensor]] = {name: [] for name in plan}
    book: dict[str, list[torch.Tensor]] = {name: [] for name in book_names}
    bounds = []
    total = 0
    declared = [name for name, ft in features.items() if ft["dtype"] != "video"]
    for name, count in zip(files, rows):
        path = folder.root / name
        wanted = list(dict.fromkeys([*plan, *book_names]))
        table = read_parquet(folder, name, wanted, declared=declared, rows=count, named_by=named_by)
        for feature in plan:
            columns[feature].append(feature_values(table, feature, features[feature], folder, path))
        for column in book_names:
            dtype = "float64" if column == "timestamp" else "int64"
            book[column].append(
                column_to_tensor(
                    table.column(column), shape=(1,), dtype=dtype, where=f"{path}: {column!r}"
                ).reshape(-1)
            )
        bounds.append((total, total + table.num_rows, path))
        total += table.num_rows
    return _Frames(columns, {k: torch.cat(v) for k, v in book.items()}, bounds, total)


def _episode_span(
    root: Path, i: int, ep: dict, major: int, frames: _Frames
) -> tuple[int, int, Path]:
    """``(begin, stop, file)``: where episode ``ep`` (the ``i``-th) lies among the frames."""
    e, length = int(ep["episode_index"]), int(ep["length"])
    if major == 3 and "dataset_from_index" in ep:
        begin, stop = int(ep["dataset_from_index"]), int(ep["dataset_to_index"])
        if stop - begin != length or begin < 0 or stop > frames.total:
            raise ValueError(
                f"{root / 'meta' / 'episodes'}: episode {e} spans frames [{begin}, {stop}) "
                f"with length {length}, the data files hold {frames.total} frames"
            )
        return begin, stop, frames.file_at(begin)
    if major == 3:
        hits = torch.nonzero(frames.episode_index == e).flatten()
        begin, stop = (int(hits[0]), int(hits[-1]) + 1) if len(hits) else (0, 0)
        path = frames.file_at(begin)
        if len(hits) != stop - begin:
            raise ValueError(f"{path}: the frames of episode {e} are not contiguous")
        return begin, stop, path
    return frames.bounds[i]


def _check_episode(ep: dict, begin: int, stop: int, path: Path, frames: _Frames) -> None:
    """The frames ``[begin, stop)`` are the episode's: its length and its index."""
    e, length = int(ep["episode_index"]), int(ep["length"])
    if stop - begin != length:
        raise ValueError(
            f"{path}: episode {e} has {stop - begin} frames, the episode metadata says {length}"
        )
    found = frames.episode_index[begin:stop].unique().tolist()
    if found != [e] and length:
        raise ValueError(
            f"{path}: frames [{begin}, {stop}) should hold episode {e}, they hold episode(s) {found}"
        )


def _frame_order(
    root: Path, info: dict, episodes: list[dict], major: int, frames: _Frames
) -> torch.Tensor:
    """``[N]`` indices of the frames in episode order; every frame in exactly one episode,
    as many as ``info.json`` declares."""
    order = []
    for i, ep in enumerate(episodes):
        begin, stop, path = _episode_span(root, i, ep, major, frames)
        _check_episode(ep, begin, stop, path, frames)
        order.append(torch.arange(begin, stop))
    index = torch.cat(order)
    n = len(index)
    if n == 0:
        raise ValueError(f"{root}: the dataset holds no frames")
    if frames.total != n or len(index.unique()) != n:
        raise ValueError(
            f"{root / 'data'}: the data files hold {frames.total} frames, the episode table covers "
            f"{len(index.unique())} of them"
        )
    check_total_frames(root, info, n)
    return index


def columns_in_order(
    root: Path,
    plan: Mapping[str, NestedKey],
    frames: _Frames,
    index: torch.Tensor,
    exact_shapes: Mapping[str, tuple[int, ...]],
) -> tuple[dict[NestedKey, torch.Tensor], dict[str, str]]:
    """Buffer key -> ``[N, ...]`` values in episode order, and feature -> key name loaded."""
    out: dict[NestedKey, torch.Tensor] = {}
    loaded: dict[str, str] = {}
    values = {name: torch.cat(frames.columns[name])[index] for name in plan}
    for name, key in plan.items():
        value = values[name]
        if name in exact_shapes:
            value = value.reshape(value.shape[0], *exact_shapes[name])
        elif key_name(key).startswith(keys.NEXT + ".") and value.ndim == 1:
            value = value.unsqueeze(-1)  # TorchRL keeps reward/done as [..., 1]
        out[key] = value
        loaded[name] = key_name(key)
    return out, loaded


def checked_frames(
    folder: OpenedFolder,
    info: dict,
    major: int,
    plan: Mapping[str, NestedKey],
    n_tasks: int,
) -> tuple[list[dict], _Frames, torch.Tensor]:
    """The episode table, the frames, and ``[N]`` the frames' order, once the frames agree
    with the episode table and with LeRobot's bookkeeping (``frame_index``, ``timestamp``,
    ``task_index``: :func:`~imitrl.datasets.lerobot._checks.check_frames`)."""
    root = folder.root
    v3_files = v3_data_files(folder) if major == 3 else None
    table = episode_table(folder, info, major, v3_files)
    if not table.num_rows:
        raise ValueError(f"{root / 'meta'}: the dataset has no episodes (nothing to load)")
    episodes = episode_dicts(table)
    files, named_by = data_files(folder, info, major, table, v3_files)
    rows = footer_frames(folder, info, major, files, named_by, v3_files, episodes)
    frames = _read_frames(folder, files, rows, named_by, plan, info["features"])
    index = _frame_order(root, info, episodes, major, frames)
    step = torch.cat([torch.arange(int(ep["length"])) for ep in episodes])
    book = {k: v[index] for k, v in frames.book.items() if k != "episode_index"}

    def file_of(i: int) -> Path:
        return frames.file_at(int(index[i]))

    check_frames(frames.episode_index[index], step, book, file_of, info["fps"], n_tasks)
    return episodes, frames, index


def timestamps(frames: _Frames, index: torch.Tensor, fps: float) -> torch.Tensor:
    """``[N]`` float64 each row's ``timestamp`` in its episode (``frame_index / fps`` where the
    dataset has no ``timestamp`` column): where its camera frames lie in the videos."""
    if "timestamp" in frames.book:
        return frames.book["timestamp"][index].double()
    return frames.frame_index[index].double() / fps
