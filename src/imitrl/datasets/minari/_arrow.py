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

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from imitrl.datasets.minari._episodes import EpisodeList, Steps, as_count, list_episodes
from imitrl.datasets.minari._spaces import decode, is_image, space_shape

__all__ = ["list_folders", "read_folder"]

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
            if not (pa.types.is_binary(node.type) or pa.types.is_large_binary(node.type)):
                raise ValueError(f"{where}: JPEG images should be binary, got {node.type}")
            return node.to_pylist()
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


def _read_table(folder: Path, fmt: str) -> pa.Table:
    """The episode's part files, in name order, as one table."""
    import pyarrow.ipc as ipc
    import pyarrow.parquet as pq

    parts = sorted(folder.glob(f"*.{fmt}"))
    if not parts:
        raise ValueError(f"{folder}: no {fmt} file (part-0.{fmt})")
    tables = []
    for part in parts:
        try:
            if fmt == "parquet":
                tables.append(pq.read_table(part))
            else:
                with pa.OSFile(str(part), "rb") as f, ipc.open_file(f) as reader:
                    tables.append(reader.read_all())
        except (pa.ArrowException, OSError) as err:
            raise ValueError(f"{part}: not a readable {fmt} file ({err})") from err
    try:
        return pa.concat_tables(tables).combine_chunks()
    except pa.ArrowException as err:
        raise ValueError(f"{folder}: its part files do not fit together ({err})") from err


def _episode_meta(folder: Path, ep_id: int) -> int | None:
    """The episode's ``metadata.json``: its id must be the folder's; its ``total_steps``."""
    path = folder / "metadata.json"
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object")
    if "id" in meta and as_count(meta["id"], "id", str(path)) != ep_id:
        raise ValueError(f"{path}: id {meta['id']!r} contradicts the folder's name")
    steps = meta.get("total_steps")
    return None if steps is None else as_count(steps, "total_steps", str(path))


def _read_folder(
    folder: Path, ep_id: int, fmt: str, spaces: tuple[dict, dict], jpeg: bool, skipped: dict
) -> Steps:
    declared = _episode_meta(folder, ep_id)
    table = _read_table(folder, fmt)
    here = f"{folder}/part-*.{fmt}"
    missing = [f for f in _FIELDS if f not in table.column_names]
    if missing or table.num_rows == 0:
        raise ValueError(f"{here}: no {missing or 'rows'} (an episode has T + 1 rows)")
    steps = table.num_rows - 1  # observations [T + 1]; the rest padded by one row
    column = {name: table.column(name).combine_chunks() for name in table.column_names}
    common = {"storage": _Columns(), "jpeg": jpeg, "skipped": skipped, "where": here}
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
    if "infos" in column and pa.types.is_struct(column["infos"].type):
        for field in column["infos"].type:
            skipped[f"infos/{field.name}"] = "per-step infos are not loaded"
    return Steps(here, ep_id, obs, act, declared_steps=declared, **flags)


def list_folders(data_dir: Path, fmt: str, meta: dict[str, Any]) -> EpisodeList:
    """The episode folders ``data/<id>/`` in id order (names starting with ``.`` or ``_``
    are ignored, as Minari's reader ignores them); only their names are read."""

    def found() -> Iterator[tuple[str, int]]:
        for entry in data_dir.iterdir():
            if not entry.is_dir() or entry.name.startswith((".", "_")):
                continue
            if not (entry.name.isascii() and entry.name.isdigit()):
                raise ValueError(f"{entry}: unexpected folder (episode folders are named by id)")
            yield entry.name, int(entry.name)

    describe = lambda name: f"{data_dir / name}/part-*.{fmt}"  # noqa: E731
    listing = list_episodes(found(), "{}", meta, str(data_dir), describe)
    if not len(listing):
        raise ValueError(f"{data_dir}: no episode folders (data/<id>/part-0.{fmt})")
    return listing


def read_folder(
    data_dir: Path,
    listing: EpisodeList,
    e: int,
    fmt: str,
    spaces: tuple[dict, dict],
    jpeg: bool,
    skipped: dict[str, str],
) -> Steps:
    """The ``e``-th episode folder (its part files only)."""
    folder = data_dir / listing.name(e)
    return _read_folder(folder, int(listing.ids[e]), fmt, spaces, jpeg, skipped)
