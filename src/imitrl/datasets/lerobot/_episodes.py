"""A LeRobot dataset's episode and task tables, read through the load's pinned folder.

v3.0: the episode table ``meta/episodes/chunk-*/file-*.parquet`` and
``meta/tasks.parquet``; v2.x: ``meta/episodes.jsonl`` and ``meta/tasks.jsonl``. Each is
validated where it is read, and the episode table against the data files' frames
before it is read (:func:`episode_table`), so that no table declaring more episodes than
the data holds is ever built. Every file is opened inside the folder
(:mod:`~imitrl.datasets.lerobot._files`); a data file that is not a readable parquet
file (truncated) is named as such, never blamed on the table that counts its frames.
"""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pyarrow as pa

from imitrl.datasets._arrow import (
    check_schema,
    checked_rows,
    footer_rows,
    parquet_file,
    read_parquet,
)
from imitrl.datasets.lerobot._files import (
    LAYOUT,
    holds,
    jsonl_lines,
    list_files,
    parse_bounded,
    parse_lines,
    read_jsonl,
)
from imitrl.datasets.lerobot._layout import DEFAULT_CHUNK_SIZE
from imitrl.fs.reading import OpenedFolder

LISTED = "the listing of data/"
"""who names a v3.0 data file: the folder's listing, as LeRobot globs it"""


def v3_data_files(folder: OpenedFolder) -> dict[str, int] | None:
    """v3.0's data files ``data/*/*.parquet`` in sorted order (as LeRobot reads them) and
    the frames each holds, from its footer; None when there is no ``data/``.

    Raises:
        ValueError: a data file that is not a readable parquet file (truncated, say),
            named.
    """
    if not holds(folder, "data"):
        return None
    files = list_files(folder, "data", suffix=".parquet", depth=1)
    return {f: footer_rows(folder, f, named_by=LISTED) for f in files}


def _frames_held(folder: OpenedFolder, major: int, v3_files: dict[str, int] | None) -> int | None:
    """v3.0: the frames in the data files; v2.x: the number of parquet files under
    ``data/``, one per episode; None if ``data/`` is absent (reported where the data is
    read)."""
    if major == 3:
        return None if v3_files is None else sum(v3_files.values())
    if not holds(folder, "data"):
        return None
    return len(list_files(folder, "data", suffix=".parquet", depth=None))


def episode_table(
    folder: OpenedFolder, info: dict, major: int, v3_files: dict[str, int] | None
) -> pa.Table:
    """The episode table in episode order, only the columns a load reads (never the
    statistics): ``episode_index``, ``length``; v3.0 ``data/chunk_index``,
    ``data/file_index``, ``dataset_from_index``/``dataset_to_index`` where a file has them
    (null where another file lacks them) and each camera's ``videos/...``; v2.x ``chunk``.
    Arrow columns: a few numbers per episode, no Python object per episode.

    Checked before anything per episode is built, so that a table declaring more
    episodes than the data holds is refused in a moment: the number of episodes against
    the frames the data files hold (``v3_files``: :func:`v3_data_files`; v2.x: against
    its episode files) before the table is read, then every length >= 1 (LeRobot refuses
    to save an empty episode), ``info.json``'s ``total_episodes``, repeated indices. So
    the episodes, and what is built per episode afterwards, never outnumber the frames on
    disk.
    """
    root = folder.root
    held = _frames_held(folder, major, v3_files)
    table = _episodes_v3(folder, held) if major == 3 else _episodes_v2(folder, info, held)
    total = info.get("total_episodes")
    if total is not None and total != table.num_rows:
        raise ValueError(
            f"{root / 'meta' / 'info.json'} declares {total} episodes, the episode metadata lists "
            f"{table.num_rows}"
        )
    lengths = table.column("length").to_numpy()
    short = np.flatnonzero(lengths < 1)
    if len(short):
        e = int(table.column("episode_index")[int(short[0])].as_py())
        raise ValueError(
            f"{root / 'meta'}: episode {e} has length {int(lengths[short[0]])} ({len(short)} "
            "episode(s) below 1 frame); every LeRobot episode holds at least one frame"
        )
    ids = table.column("episode_index").to_numpy()
    unique, counts = np.unique(ids, return_counts=True)
    if len(unique) != len(ids):
        again = unique[counts > 1][:10].tolist()
        raise ValueError(f"{root / 'meta'}: episode indices repeat (first: {again})")
    return table


def _too_many(where: Path, declared: int, held: int | None, of: str) -> None:
    if held is not None and declared > held:
        raise ValueError(
            f"{where}: lists {declared} episodes, the data holds {held} {of}; every episode "
            "holds at least one frame (refused before the table is read)"
        )


def episode_dicts(table: pa.Table) -> list[dict]:
    """Rows of :func:`episode_table` as dicts, one per episode, without the entries its
    file lacked."""
    return [{k: v for k, v in ep.items() if v is not None} for ep in table.to_pylist()]


_NEED = ["episode_index", "length", "data/chunk_index", "data/file_index"]
_OPTIONAL = ["dataset_from_index", "dataset_to_index"]


def _episodes_v3(folder: OpenedFolder, held: int | None) -> pa.Table:
    """The v3.0 episode files, each opened once: their footers counted against ``held``,
    then the columns a load reads."""
    ep_dir = folder.root / "meta" / "episodes"
    files = list_files(folder, "meta/episodes", suffix=".parquet", depth=1)
    if not files:
        raise ValueError(
            f"{ep_dir}: no episode metadata files (meta/episodes/chunk-*/file-*.parquet)"
        )
    tables = []
    with ExitStack() as stack:
        # not pq.read_table: its pre-buffering reads the statistics columns too
        opened = [
            stack.enter_context(parquet_file(folder, f, named_by=LAYOUT, pre_buffer=False))
            for f in files
        ]
        listed = sum(checked_rows(pf, folder.root / f) for f, pf in zip(files, opened))
        _too_many(ep_dir, listed, held, "frames")
        for f, pf in zip(files, opened):
            tables.append(_episode_columns(folder.root / f, pf))
    try:
        table = pa.concat_tables(tables, promote_options="permissive")
    except pa.ArrowException as err:
        raise ValueError(f"{ep_dir}: the episode metadata files disagree ({err})") from err
    return table.sort_by("episode_index").combine_chunks()


def _episode_columns(where: Path, pf) -> pa.Table:
    """The columns of one v3.0 episode file a load reads; none may hold a null."""
    schema = pf.schema_arrow
    check_schema(where, schema, None, None)
    missing = [c for c in _NEED if c not in schema.names]
    if missing:
        raise ValueError(f"{where}: episode metadata lacks column(s) {missing}")
    # where each camera's frames lie: videos/<feature>/{chunk_index, file_index,
    # from_timestamp, to_timestamp} (checked where the videos are read)
    cameras = [c for c in schema.names if c.startswith("videos/")]
    columns = _NEED + [c for c in _OPTIONAL if c in schema.names] + cameras
    try:
        table = pf.read(columns=columns)
    except (pa.ArrowException, OSError) as err:
        raise ValueError(f"{where}: cannot read the parquet data ({err})") from err
    nulls = [c for c in table.column_names if table.column(c).null_count]
    if nulls:
        raise ValueError(f"{where}: episode metadata column(s) {nulls} hold null entries")
    return table


def _episodes_v2(folder: OpenedFolder, info: dict, held: int | None) -> pa.Table:
    root = folder.root
    path = root / "meta" / "episodes.jsonl"
    lines = jsonl_lines(
        folder, "meta/episodes.jsonl", why="a v2.x LeRobot dataset lists its episodes there"
    )
    _too_many(path, len(lines), held, "episode files")
    episodes = parse_lines(lines, where=path)
    for ep in episodes:
        for field in ("episode_index", "length"):
            if not isinstance(ep, dict) or not isinstance(ep.get(field), int):
                raise ValueError(f"{path}: entry {ep!r} has no integer {field!r}")
    chunks = info.get("chunks_size", DEFAULT_CHUNK_SIZE)
    if isinstance(chunks, bool) or not isinstance(chunks, int) or chunks < 1:
        raise ValueError(f"{root / 'meta' / 'info.json'}: chunks_size must be >= 1, got {chunks!r}")
    ids = np.array([ep["episode_index"] for ep in episodes], dtype=np.int64)
    table = pa.table(
        {
            "episode_index": ids,
            "length": np.array([ep["length"] for ep in episodes], dtype=np.int64),
            "chunk": ids // chunks,
        }
    )
    return table.sort_by("episode_index")


def read_tasks(folder: OpenedFolder, major: int) -> list[str]:
    """The task strings, indexed by ``task_index`` (which must run 0..T-1)."""
    pairs = _task_pairs_v2(folder) if major == 2 else _task_pairs_v3(folder)
    pairs.sort()
    tasks = [t for _, t in pairs]
    if [i for i, _ in pairs] != list(range(len(pairs))):
        raise ValueError(f"{folder.root / 'meta'}: task indices are not 0..{len(pairs) - 1}")
    return tasks


def _task_pairs_v2(folder: OpenedFolder) -> list[tuple[int, str]]:
    path = folder.root / "meta" / "tasks.jsonl"
    rows = read_jsonl(
        folder, "meta/tasks.jsonl", why="a v2.x LeRobot dataset lists its tasks there"
    )
    for r in rows:
        if not (
            isinstance(r, dict)
            and isinstance(r.get("task_index"), int)
            and isinstance(r.get("task"), str)
        ):
            raise ValueError(f"{path}: entry {r!r} needs an integer 'task_index' and a 'task'")
    return [(r["task_index"], r["task"]) for r in rows]


def _task_pairs_v3(folder: OpenedFolder) -> list[tuple[int, str]]:
    path = folder.root / "meta" / "tasks.parquet"
    if not holds(folder, "meta/tasks.parquet"):
        raise ValueError(f"{path}: file not found")
    table = read_parquet(folder, "meta/tasks.parquet", named_by=LAYOUT)
    where = f"{path}: its pandas metadata"
    pandas_meta = parse_bounded((table.schema.metadata or {}).get(b"pandas", b"{}"), where)
    index = pandas_meta.get("index_columns", []) if isinstance(pandas_meta, dict) else []
    index_cols = [c for c in index if isinstance(c, str)] if isinstance(index, list) else []
    for name in (*index_cols, "task", "__index_level_0__"):
        if name in table.column_names:
            strings = table.column(name).to_pylist()
            break
    else:
        raise ValueError(f"{path}: no task string column (pandas index or 'task')")
    if "task_index" not in table.column_names:
        raise ValueError(f"{path}: no 'task_index' column")
    indices = table.column("task_index").to_pylist()
    if not all(isinstance(i, int) for i in indices) or not all(isinstance(t, str) for t in strings):
        raise ValueError(f"{path}: needs an integer task_index and a string task in every row")
    return list(zip(indices, strings))
