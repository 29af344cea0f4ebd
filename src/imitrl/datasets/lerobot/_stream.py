"""A LeRobot dataset streamed into a buffer, whole episodes at a time
(``load_lerobot(..., into=buffer)``).

Where each episode's frames lie comes from the metadata alone (v3.0: the episode table's
``dataset_from_index``/``dataset_to_index`` in the sorted data files, or one pass over the
``episode_index`` column; v2.x: one file per episode), and is checked before any frame is
read: the episodes cover every frame once, as many as ``info.json`` declares. The
episodes are then read in pieces of about :data:`PIECE_ROWS` frames (whole episodes, at
least one), only the row groups holding them, converted and checked exactly as
:func:`load_lerobot` checks a whole dataset, and turned into rows.

Nothing half-loaded (:mod:`imitrl.datasets._streaming`): the pieces are read twice. The
first pass runs every check, the buffer's own included; only then does the second pass
extend the buffer, piece by piece. A bad file anywhere leaves the buffer as it was. Resident memory: one
piece (the allocators' unused memory is handed back after each:
:func:`~imitrl.datasets._arrow.release_unused_memory`) and a few integers per episode (the
episode table's columns, never its statistics: :class:`Source`), whatever the dataset's
length.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._arrow import (
    check_schema,
    checked_rows,
    column_to_tensor,
    parquet_file,
    read_parquet,
)
from imitrl.datasets._common import NestedKey, conform_to_env, key_name, required_rows
from imitrl.datasets._streaming import check_pieces, extend_pieces
from imitrl.datasets.lerobot._checks import check_frames
from imitrl.datasets.lerobot._episodes import episode_dicts
from imitrl.datasets.lerobot._interventions import (
    RoundOrder,
    check_dagger_columns,
    feature_values,
    own_episodes,
    own_ids_follow,
)
from imitrl.datasets.lerobot._layout import data_file
from imitrl.datasets.lerobot._video import decode_videos
from imitrl.fs.reading import OpenedFolder

PIECE_ROWS = 1 << 17
"""frames read, checked and added to the buffer at once (rounded to whole episodes)"""


@dataclass(frozen=True)
class Source:
    """What a streamed load reads: the data files and where each episode lies in them.
    Per episode: a few integers (``ids``, ``lengths``, ``spans``) and the episode table's
    columns (arrow), turned into dicts a piece at a time; nothing per frame."""

    folder: OpenedFolder
    """the dataset folder, pinned: every file is opened inside it"""
    info: dict
    major: int
    episodes: pa.Table
    """the episode table, in episode order (:func:`~imitrl.datasets.lerobot._episodes.episode_table`)"""
    files: list[str]
    """the data files (relative to the folder), in order"""
    named_by: str
    """who names the data files, for messages"""
    bounds: np.ndarray
    """``[F + 1]`` first frame of each file (and the total) in their concatenation"""
    spans: np.ndarray
    """``[E, 2]`` each episode's ``[begin, stop)`` in that concatenation"""
    ids: np.ndarray
    """``[E]`` each episode's ``episode_index``"""
    lengths: np.ndarray
    """``[E]`` each episode's ``length``"""

    @property
    def root(self) -> Path:
        return self.folder.root

    def file_of(self, frame: int) -> Path:
        return self.root / self.files[int(np.searchsorted(self.bounds, frame, side="right")) - 1]


def _runs(
    folder: OpenedFolder, files: list[str], bounds: np.ndarray, named_by: str
) -> dict[int, tuple[int, int]]:
    """episode index -> ``[begin, stop)`` from the ``episode_index`` column, read one file at
    a time (v3.0 without ``dataset_from_index``); each episode must be one run of frames."""
    spans: dict[int, tuple[int, int]] = {}
    last = None
    for name, first, end in zip(files, bounds[:-1], bounds[1:]):
        path = folder.root / name
        rows = int(end - first)  # as its footer was counted
        table = read_parquet(folder, name, ["episode_index"], rows=rows, named_by=named_by)
        column = table.column("episode_index")
        read = column_to_tensor(column, shape=(1,), dtype="int64", where=f"{path}: 'episode_index'")
        ids = read.reshape(-1).numpy()
        change = np.flatnonzero(np.diff(ids)) + 1
        for s, e in zip(np.r_[0, change], np.r_[change, len(ids)]):
            i = int(ids[s])
            if i == last and i in spans:  # the run goes on from the previous file
                spans[i] = (spans[i][0], int(first + e))
            elif i in spans:
                raise ValueError(f"{path}: the frames of episode {i} are not contiguous")
            else:
                spans[i] = (int(first + s), int(first + e))
        last = int(ids[-1]) if len(ids) else last
    return spans


def locate(
    folder: OpenedFolder,
    info: dict,
    major: int,
    episodes: pa.Table,
    files: list[str],
    counts: list[int],
    named_by: str,
) -> Source:
    """Every episode's frames in the data ``files`` (relative names, in order, holding the
    ``counts`` of frames their footers declare), checked against the metadata (lengths,
    one episode per frame, ``total_frames``) before any frame is read."""
    root = folder.root
    bounds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    total = int(bounds[-1])
    ids = episodes.column("episode_index").to_numpy().astype(np.int64)
    lengths = episodes.column("length").to_numpy().astype(np.int64)
    given = [c for c in ("dataset_from_index", "dataset_to_index") if c in episodes.column_names]
    if major != 3:
        spans = np.stack([bounds[:-1], bounds[1:]], axis=1)
    elif len(given) == 2 and not any(episodes.column(c).null_count for c in given):
        spans = np.stack([episodes.column(c).to_numpy() for c in given], axis=1)
        spans = spans.astype(np.int64)
    else:
        found = _runs(folder, files, bounds, named_by)
        spans = np.array([found.get(e, (0, 0)) for e in ids.tolist()], dtype=np.int64)
        spans = spans.reshape(len(ids), 2)
    bad = np.flatnonzero(
        (spans[:, 1] - spans[:, 0] != lengths) | (spans[:, 0] < 0) | (spans[:, 1] > total)
    )
    if len(bad):
        k = int(bad[0])
        e, (begin, stop) = int(ids[k]), spans[k].tolist()
        if major == 3:
            where = root / "meta" / "episodes"
        else:
            where = root / data_file(root, info, major, episode_dicts(episodes.slice(k, 1))[0])
        raise ValueError(
            f"{where}: episode {e} spans frames [{begin}, {stop}) with length {int(lengths[k])}, "
            f"the data files hold {total} frames"
        )
    order = np.sort(spans[:, 0])
    ends = np.sort(spans[:, 1])
    covered = int((spans[:, 1] - spans[:, 0]).sum())
    if covered == 0:
        raise ValueError(f"{root}: the dataset holds no frames")
    if covered != total or (len(order) > 1 and (order[1:] < ends[:-1]).any()):
        raise ValueError(
            f"{root / 'data'}: the data files hold {total} frames, the episode table covers "
            f"{covered} frames of them (overlapping or missing)"
        )
    if info.get("total_frames") is not None and info["total_frames"] != total:
        raise ValueError(
            f"{root / 'meta' / 'info.json'} declares {info['total_frames']} frames, the data "
            f"files hold {total}"
        )
    return Source(folder, info, major, episodes, files, named_by, bounds, spans, ids, lengths)


def _read_span(src: Source, begin: int, stop: int, names: list[str]) -> list[tuple[Path, pa.Table]]:
    """Frames ``[begin, stop)`` of the concatenated data files: the row groups holding them,
    file by file, each with its file (for messages).

    Read through a memory map, one thread: the compressed pages are the file's own pages,
    not buffers of pyarrow's pool, whose sizes differ from file to file and leave the
    pool fragmented (measured: +35 MB of resident memory over 150 reads of 50 files,
    none this way); the map goes once the piece is done."""
    declared = [n for n, ft in src.info["features"].items() if ft["dtype"] != "video"]
    out = []
    first = int(np.searchsorted(src.bounds, begin, side="right")) - 1
    for f in range(first, len(src.files)):
        lo, hi = int(src.bounds[f]), int(src.bounds[f + 1])
        if lo >= stop:
            break
        path = src.root / src.files[f]
        with parquet_file(src.folder, src.files[f], named_by=src.named_by, memory_map=True) as pf:
            check_schema(path, pf.schema_arrow, names, declared)
            checked_rows(pf, path, hi - lo)  # as counted when the episodes were located
            try:
                sizes = [pf.metadata.row_group(g).num_rows for g in range(pf.num_row_groups)]
                starts = lo + np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
                groups = [
                    g for g in range(len(sizes)) if starts[g] < stop and starts[g + 1] > begin
                ]
                table = pf.read_row_groups(groups, columns=names, use_threads=False)
            except (pa.ArrowException, OSError) as err:
                raise ValueError(f"{path}: cannot read the parquet data ({err})") from err
        skip = max(begin, lo) - int(starts[groups[0]]) if groups else 0
        out.append((path, table.slice(skip, min(stop, hi) - max(begin, lo))))
    return out


@dataclass(frozen=True)
class Piece:
    """Some consecutive episodes of the episode table, read and checked."""

    columns: dict[str, torch.Tensor]
    """planned feature -> ``[n, *shape]``"""
    book: dict[str, torch.Tensor]
    """``[n]`` episode_index, frame_index (and timestamp, task_index where declared)"""
    file_of: Callable[[int], Path]
    """row -> its data file"""


def read_piece(
    src: Source, first: int, end: int, plan: Mapping[str, NestedKey], n_tasks: int
) -> Piece:
    """Episodes ``first .. end - 1`` (episode order), checked as :func:`load_lerobot` checks
    a whole dataset: values against the declared dtypes and shapes, lengths and indices
    against the episode table, ``frame_index``, ``timestamp`` and ``task_index``."""
    features = src.info["features"]
    book_names = ["episode_index", "frame_index"]
    book_names += [c for c in ("timestamp", "task_index") if c in features]
    names = list(dict.fromkeys([*plan, *book_names]))
    ranges: list[list[int]] = []  # the episodes' spans, merged where they touch
    for begin, stop in src.spans[first:end].tolist():
        if ranges and ranges[-1][1] == begin:
            ranges[-1][1] = stop
        else:
            ranges.append([begin, stop])
    parts: list[tuple[Path, pa.Table]] = []
    for begin, stop in ranges:
        parts.extend(_read_span(src, begin, stop, names))
    columns: dict[str, list[torch.Tensor]] = {n: [] for n in names}
    rows_file: list[tuple[int, Path]] = []
    at = 0
    for path, table in parts:
        for name in names:
            if name in plan:
                value = feature_values(table, name, features[name], src.folder, path)
            else:
                where = f"{path}: {name!r}"
                dtype = "float64" if name == "timestamp" else "int64"
                value = column_to_tensor(table.column(name), shape=(1,), dtype=dtype, where=where)
                value = value.reshape(-1)
            columns[name].append(value)
        rows_file.append((at, path))
        at += table.num_rows
    cat = {n: torch.cat(v) for n, v in columns.items()}
    starts = [s for s, _ in rows_file]

    def file_of(i: int) -> Path:
        return rows_file[int(np.searchsorted(starts, i, side="right")) - 1][1]

    step = _check_episodes(src, first, end, cat["episode_index"], file_of)
    book = {k: cat[k] for k in book_names}
    check_frames(
        book["episode_index"],
        step,
        {k: v for k, v in book.items() if k != "episode_index"},
        file_of,
        src.info["fps"],
        n_tasks,
    )
    return Piece({n: cat[n] for n in plan}, book, file_of)


def _check_episodes(
    src: Source, first: int, end: int, episode: torch.Tensor, file_of: Callable[[int], Path]
) -> torch.Tensor:
    """The frames read are the episodes': each block holds its own index only; returns
    ``[n]`` 0..length-1 in each episode (what ``frame_index`` must read)."""
    lengths, ids = src.lengths[first:end], src.ids[first:end]
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    wrong = np.flatnonzero(episode.numpy() != np.repeat(ids, lengths))
    if len(wrong):
        k = int(np.searchsorted(starts, wrong[0], side="right")) - 1
        at, n = int(starts[k]), int(lengths[k])
        found = episode[at : at + n].unique().tolist()
        raise ValueError(
            f"{file_of(at)}: frames [{at}, {at + n}) of this read should hold episode "
            f"{int(ids[k])}, they hold episode(s) {found}"
        )
    return torch.from_numpy(np.arange(int(lengths.sum())) - np.repeat(starts, lengths))


def pieces(src: Source) -> list[tuple[int, int]]:
    """``(first, end)`` episodes of each piece: about :data:`PIECE_ROWS` frames, whole
    episodes."""
    out, first, rows = [], 0, 0
    for e, n in enumerate(src.lengths.tolist()):
        if rows and rows + n > PIECE_ROWS:
            out.append((first, e))
            first, rows = e, 0
        rows += n
    out.append((first, len(src.lengths)))
    return out


@dataclass
class Settings:
    """How a piece's frames become rows (as :func:`load_lerobot` makes them)."""

    plan: Mapping[str, NestedKey]
    cameras: Mapping[str, NestedKey]
    exact_shapes: Mapping[str, tuple[int, ...]]
    n_tasks: int
    first_episode: int
    env: EnvBase | None
    names: dict[str, str]
    """buffer key name -> feature, for messages"""
    own_ids: bool | None = None
    """imitrl's own episode ids kept in every piece (True), dropped from every piece
    (False), or decided piece by piece (None: the dataset has none, or no pass 1 ran):
    :func:`check_stream` decides it for the whole dataset"""


def piece_rows(
    src: Source, first: int, end: int, s: Settings, notes: list[str], order: RoundOrder
) -> TensorDict:
    """The rows of episodes ``first .. end - 1``, checked (``order``: the rounds of the
    pieces before), videos decoded, fitted to ``env``."""
    piece = read_piece(src, first, end, s.plan, s.n_tasks)
    out: dict[NestedKey, torch.Tensor] = {}
    for name, key in s.plan.items():
        value = piece.columns[name]
        if name in s.exact_shapes:
            value = value.reshape(value.shape[0], *s.exact_shapes[name])
        elif key_name(key).startswith(keys.NEXT + ".") and value.ndim == 1:
            value = value.unsqueeze(-1)  # TorchRL keeps reward/done as [..., 1]
        out[key] = value
    frame_index = piece.book["frame_index"]
    flag = s.names.get(key_name(keys.EXPERT_EXECUTED), "intervention")
    check_dagger_columns(out, piece.book["episode_index"], frame_index, piece.file_of, order, flag)
    if s.cameras:
        times = piece.book.get("timestamp")
        times = frame_index.double() / src.info["fps"] if times is None else times.double()
        episodes = episode_dicts(src.episodes.slice(first, end - first))
        out.update(decode_videos(src.folder, src.info, src.major, episodes, s.cameras, times, None))
    own_episodes(out, piece.book["episode_index"], piece.file_of, keep=s.own_ids)
    episode = out.pop(keys.EPISODE) if keys.EPISODE in out else piece.book["episode_index"]
    rows = required_rows(out, episode=episode, step=frame_index, first_episode=s.first_episode)
    if s.env is not None:
        where = str(src.root / "meta" / "info.json")
        found: list[str] = []
        rows = conform_to_env(rows, s.env, where=where, notes=found, names=s.names)
        notes.extend(n for n in found if n not in notes)
    return rows


def check_stream(buffer: DemonstrationBuffer, src: Source, s: Settings) -> list[str]:
    """Pass 1: every piece read and checked (the buffer's checks included), nothing added;
    returns the notes of :func:`conform_to_env`."""
    notes: list[str] = []
    order = RoundOrder()
    s.own_ids = _own_ids_follow(src, s)
    check_pieces(buffer, (piece_rows(src, f, e, s, notes, order) for f, e in pieces(src)), src.root)
    return notes


def _own_ids_follow(src: Source, s: Settings) -> bool | None:
    """Whether imitrl's own episode ids follow LeRobot's episodes across the whole dataset
    (None: it has none), read piece by piece from their two columns alone: a piece decides
    nothing alone, as ids unique in each piece may repeat across pieces (a merge), which
    the whole-dataset load answers by taking LeRobot's ``episode_index``."""
    own = [name for name, key in s.plan.items() if key == keys.EPISODE]
    if not own:
        return None
    plan = {own[0]: keys.EPISODE}
    parts = (
        (piece.columns[own[0]], piece.book["episode_index"])
        for piece in (read_piece(src, f, e, plan, s.n_tasks) for f, e in pieces(src))
    )
    return own_ids_follow(parts, src.root)


def extend_stream(buffer: DemonstrationBuffer, src: Source, s: Settings) -> TensorDictBase:
    """Pass 2: the pieces :func:`check_stream` checked, added to ``buffer``; returns the
    rows added (a view of the buffer)."""
    order = RoundOrder()
    return extend_pieces(buffer, (piece_rows(src, f, e, s, [], order) for f, e in pieces(src)))
