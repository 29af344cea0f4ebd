"""Minari's ``arrow`` (and ``parquet``) storage (``minari/dataset/_storages/arrow_storage.py``,
Minari 0.5)::

    <dataset>/data/metadata.json         as for hdf5, with data_format "arrow" / "parquet"
    <dataset>/data/<id>/part-0.arrow     one folder per episode (``pyarrow.dataset`` partitions
                                         on episode_id): an Arrow IPC file (parquet: part-0.parquet)
                                         of T + 1 rows; observations [T+1], actions, rewards,
                                         terminations, truncations padded with one last row,
                                         infos (a struct column) when recorded
    <dataset>/data/<id>/metadata.json    {"id", "total_steps", "seed"?, "options"?}

Vectors (Box, MultiDiscrete, MultiBinary) are fixed-size lists of the flattened per-step
array, Discrete a plain integer column, a Dict/Tuple a struct (Tuple fields named
``"0"``, ``"1"``, ...: loaded as ``_index_<i>`` as the hdf5 storage names them), images
JPEG bytes when ``jpeg_encoding``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from imitrl.datasets.minari._bounds import Floor, check_declared, step_bytes
from imitrl.datasets.minari._episodes import EpisodeList, Steps, as_count, list_episodes
from imitrl.datasets.minari._ipc import declared_sizes, read_ipc
from imitrl.datasets.minari._spaces import decode, is_image, space_shape
from imitrl.fs.reading import OpenedFolder, fd_path, parse_json

__all__ = ["EpisodeFiles", "list_folders", "open_episode", "read_episode"]

_FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


def _is_list(t: pa.DataType) -> bool:
    return pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t)


class _Columns:
    """A space's values in an arrow column: a struct per Dict/Tuple, a list per vector."""

    def child(self, node: pa.Array, name: str, kind: str, where: str) -> pa.Array:
        if not pa.types.is_struct(node.type):
            raise ValueError(f"{where.rsplit('/', 1)[0]} should be a struct for a {kind} space")
        field = name.removeprefix("_index_") if kind == "Tuple" else name
        if node.type.get_field_index(field) < 0:
            raise ValueError(f"{where} is missing")
        return node.field(field)

    def leaf(self, node: pa.Array, space: dict, jpeg: bool, where: str) -> Any:
        if node.null_count:
            raise ValueError(f"{where}: contains null entries")
        if jpeg and is_image(space):
            kind = node.type.value_type if pa.types.is_dictionary(node.type) else node.type
            if not (pa.types.is_binary(kind) or pa.types.is_large_binary(kind)):
                raise ValueError(f"{where}: JPEG images should be binary, got {node.type}")
            return (node[i].as_py() for i in range(len(node)))  # one image at a time
        shape = space_shape(space)
        if not _is_list(node.type):
            if not (pa.types.is_integer(node.type) or pa.types.is_floating(node.type)):
                if not pa.types.is_boolean(node.type):
                    raise ValueError(f"{where}: holds {node.type} values, expected numbers")
            values = node.to_numpy(zero_copy_only=False)
            return values.reshape(len(node), *shape) if shape == (1,) else values
        lengths = pc.list_value_length(node).to_numpy(zero_copy_only=False)
        if (lengths != math.prod(shape)).any():
            bad = int(lengths[lengths != math.prod(shape)][0])
            raise ValueError(f"{where}: {bad} values in a step, the space's shape is {list(shape)}")
        flat = node.flatten()
        if flat.null_count or _is_list(flat.type):
            raise ValueError(f"{where}: nulls or nested lists where numbers are expected")
        return flat.to_numpy(zero_copy_only=False).reshape(len(node), *shape)


def _rows_of(where: str, rows: int) -> str:
    return f"{where}: {rows:,} rows of {', '.join(_FIELDS)}"


_LEAF_BYTES = {"BOOLEAN": 1, "INT32": 4, "INT64": 8, "INT96": 12, "FLOAT": 4, "DOUBLE": 8}


def _parquet_table(
    fd: int, where: str, row_bytes: int, size: int, floor: Floor
) -> tuple[pa.Table, pa.Schema]:
    """A parquet part file's five step columns, once its footer's sizes fit its bytes: the
    rows times the bytes a step loads into, and the leaf values times their width (a
    run-length or dictionary page can declare millions of values in a few bytes); binary
    columns (encoded images) are read as dictionaries, so one stored value named by many
    rows is not copied for each."""
    import pyarrow.parquet as pq

    pf = pq.ParquetFile(fd_path(fd))
    meta = pf.metadata
    rows = meta.num_rows
    check_declared(
        rows * row_bytes, size, compressed=True, where=_rows_of(where, rows), floor=floor
    )
    leaves, binary = 0, set()
    for g in range(meta.num_row_groups):
        group = meta.row_group(g)
        for c in range(group.num_columns):
            column = group.column(c)
            if column.path_in_schema.split(".")[0] not in _FIELDS:
                continue
            width = _LEAF_BYTES.get(column.physical_type)
            if width is None:  # BYTE_ARRAY, FIXED_LEN_BYTE_ARRAY: as stored
                binary.add(column.path_in_schema)
                leaves += column.total_uncompressed_size
            else:
                leaves += column.num_values * width
    check_declared(
        leaves, size, compressed=True, where=f"{where}: its columns' values", floor=floor
    )
    missing = [f for f in _FIELDS if f not in pf.schema_arrow.names]
    if missing:
        raise ValueError(f"{where}: no {missing} (an episode has T + 1 rows)")
    schema = pf.schema_arrow
    pf = pq.ParquetFile(fd_path(fd), read_dictionary=sorted(binary) or None)
    return pf.read(columns=list(_FIELDS)), schema


def _arrow_table(
    fd: int, where: str, row_bytes: int, size: int, floor: Floor
) -> tuple[pa.Table, pa.Schema]:
    """An Arrow IPC part file, read whole (its own size), once the rows and the
    uncompressed bytes its messages declare fit its bytes (:mod:`._ipc`)."""
    with pa.OSFile(fd_path(fd), "rb") as f:
        data = f.read_buffer(size)
    rows, unpacked = declared_sizes(data)
    check_declared(
        rows * row_bytes, size, compressed=True, where=_rows_of(where, rows), floor=floor
    )
    buffers = f"{where}: its compressed buffers"
    check_declared(unpacked, size, compressed=True, where=buffers, floor=floor)
    table = read_ipc(data)
    return table.select([f for f in _FIELDS if f in table.column_names]), table.schema


def _read_table(
    parts: list[tuple[str, int]], fmt: str, row_bytes: int, here: str, ep_id: int, floor: Floor
) -> tuple[pa.Table, pa.Schema]:
    """Episode ``ep_id``'s part files (``(name, descriptor)``, in name order) as one table,
    and the first one's schema; ``row_bytes``: what one step of the five columns loads
    into; the sizes they declare within the load's ``floor``."""
    if not parts:
        raise ValueError(f"{here}: no {fmt} file (part-0.{fmt})")
    read = _parquet_table if fmt == "parquet" else _arrow_table
    tables, schemas = [], []
    for name, fd in parts:
        try:
            where = f"{name} (episode {ep_id})"
            table, schema = read(fd, where, row_bytes, os.fstat(fd).st_size, floor)
        except (pa.ArrowException, OSError) as err:
            raise ValueError(f"{name}: not a readable {fmt} file ({err})") from err
        tables.append(table)
        schemas.append(schema)
    try:
        return pa.concat_tables(tables).combine_chunks(), schemas[0]
    except pa.ArrowException as err:
        raise ValueError(f"{here}: its part files do not fit together ({err})") from err


def _episode_meta(meta: bytes | None, where: str, ep_id: int) -> int | None:
    """The episode's ``metadata.json`` (its bytes, or None when absent): its id must be
    the folder's; its ``total_steps``."""
    if meta is None:
        return None
    found = parse_json(meta, where=where)
    if not isinstance(found, dict):
        raise ValueError(f"{where}: expected a JSON object")
    if "id" in found and as_count(found["id"], "id", where) != ep_id:
        raise ValueError(f"{where}: id {found['id']!r} contradicts the folder's name")
    steps = found.get("total_steps")
    return None if steps is None else as_count(steps, "total_steps", where)


EPISODE_META_LIMIT = 1 << 20
"""bytes an episode's ``metadata.json`` may hold (Minari writes a few dozen)"""


@dataclass
class EpisodeFiles:
    """One episode folder's files, opened inside the dataset folder: each part file's
    descriptor (in name order) and the bytes of its ``metadata.json`` (None: absent)."""

    folder: Path
    parts: list[tuple[str, int]] = field(default_factory=list)
    """``(path, descriptor)`` of each ``*.<fmt>`` file"""
    meta: bytes | None = None

    def close(self) -> None:
        """Close the part files' descriptors."""
        for _, fd in self.parts:
            os.close(fd)
        self.parts = []


def open_episode(folder: OpenedFolder, name: str, fmt: str) -> EpisodeFiles:
    """The files of episode folder ``name``, each opened once by descriptor inside
    ``folder`` (a regular file, never a FIFO or a link out)."""
    files = EpisodeFiles(folder.root / name)
    named_by = f"episode folder {name}"
    try:
        listed = folder.entries(name, named_by=named_by)  # through the pinned descriptor
        for part in sorted(n for n, is_dir in listed if not is_dir and n.endswith(f".{fmt}")):
            path = str(files.folder / part)
            files.parts.append((path, folder.open(f"{name}/{part}", named_by=named_by)))
        if any(n == "metadata.json" for n, _ in listed):
            files.meta = folder.read_bytes(
                f"{name}/metadata.json", named_by=named_by, limit=EPISODE_META_LIMIT
            )
    except BaseException:
        files.close()
        raise
    return files


def read_episode(
    files: EpisodeFiles,
    ep_id: int,
    fmt: str,
    spaces: tuple[dict, dict],
    jpeg: bool,
    skipped: dict[str, str],
    floor: Floor,
) -> Steps:
    """Episode ``ep_id`` from its opened files, its sizes checked before it is read, within
    the load's ``floor`` (per-step infos are listed in ``skipped``, not read)."""
    here = f"{files.folder}/part-*.{fmt}"
    declared = _episode_meta(files.meta, str(files.folder / "metadata.json"), ep_id)
    row_bytes = step_bytes(spaces[0], jpeg) + step_bytes(spaces[1], jpeg) + 8 + 1 + 1
    table, schema = _read_table(files.parts, fmt, row_bytes, here, ep_id, floor)
    missing = [f for f in _FIELDS if f not in table.column_names]
    if missing or table.num_rows == 0:
        raise ValueError(f"{here}: no {missing or 'rows'} (an episode has T + 1 rows)")
    steps = table.num_rows - 1  # observations [T + 1]; the rest padded by one row
    column = {name: table.column(name).combine_chunks() for name in _FIELDS}
    common: dict[str, Any] = {
        "storage": _Columns(),
        "jpeg": jpeg,
        "skipped": skipped,
        "where": here,
    }
    obs = decode(column["observations"], spaces[0], "observations", **common)
    act = decode(column["actions"].slice(0, steps), spaces[1], "actions", **common)
    if obs is None or act is None:
        raise ValueError(f"{here}: observations and actions must be numeric")
    flags = {}
    for name in ("rewards", "terminations", "truncations"):
        col = column[name].slice(0, steps)
        if col.null_count or _is_list(col.type) or pa.types.is_struct(col.type):
            raise ValueError(f"{here}: {name} should be one number per step, got {col.type}")
        flags[name] = col.to_numpy(zero_copy_only=False)
    index = schema.get_field_index("infos")  # listed from the schema, never read
    if index >= 0 and pa.types.is_struct(schema.field(index).type):
        for sub in schema.field(index).type:
            skipped[f"infos/{sub.name}"] = "per-step infos are not loaded"
    return Steps(here, ep_id, obs, act, declared_steps=declared, **flags)


def list_folders(folder: OpenedFolder, fmt: str, meta: dict[str, Any]) -> EpisodeList:
    """The episode folders ``data/<id>/`` of the pinned ``folder`` (its ``data`` folder)
    in id order (names starting with ``.`` or ``_`` are ignored, as Minari's reader
    ignores them); only their names are read."""
    data_dir = folder.root

    def found() -> Iterator[tuple[str, int]]:
        for name, is_dir in folder.entries(named_by="the Minari layout"):
            if not is_dir or name.startswith((".", "_")):
                continue
            if not (name.isascii() and name.isdigit()):
                raise ValueError(
                    f"{data_dir / name}: unexpected folder (episode folders are named by id)"
                )
            yield name, int(name)

    describe = lambda name: f"{data_dir / name}/part-*.{fmt}"  # noqa: E731
    listing = list_episodes(found(), "{}", meta, str(data_dir), describe)
    if not len(listing):
        raise ValueError(f"{data_dir}: no episode folders (data/<id>/part-0.{fmt})")
    return listing
