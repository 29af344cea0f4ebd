"""What a LeRobot dataset's ``meta/`` directory says.

The format's constants (versions, path templates, the column <-> key maps), and reading
``meta/info.json``, the episode table (v3.0 parquet or v2.x ``episodes.jsonl``) and the
task table, each validated where it is read. (Finding a dataset on disk:
:mod:`~imitrl.datasets.lerobot._locate`.)
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from imitrl import keys
from imitrl.datasets._arrow import check_schema, read_parquet
from imitrl.datasets._common import NestedKey, key_name
from imitrl.fs.contained import inside

DEFAULT_KEY_MAP: dict[str, NestedKey] = {
    "observation.state": keys.OBSERVATION,
    "action": keys.EXPERT_ACTION,
    "next.reward": (keys.NEXT, keys.REWARD),
    "next.done": (keys.NEXT, keys.DONE),
    "next.terminated": (keys.NEXT, keys.TERMINATED),
    "next.truncated": (keys.NEXT, keys.TRUNCATED),
    "observation.environment_state": keys.ENVIRONMENT_STATE,
}
"""dataset feature -> buffer key, applied unless ``key_map`` overrides an entry (``task_index``
is loaded as ``"task_index"`` when the dataset has more than one task)"""

IMITRL_COLUMNS: dict[str, NestedKey] = {
    "imitrl.executed_action": keys.ACTION,
    "imitrl.expert_executed": keys.EXPERT_EXECUTED,
    "imitrl.round": keys.ROUND,
    "imitrl.episode": keys.EPISODE,
}
"""the columns :func:`save_lerobot` adds so that DAgger rounds round-trip"""

# LeRobot's bookkeeping columns (DEFAULT_FEATURES in lerobot/datasets/utils.py)
BOOKKEEPING = ("timestamp", "frame_index", "episode_index", "index", "task_index")
CODEBASE_VERSION = "v3.0"
READ_VERSIONS = {"v2.0": 2, "v2.1": 2, "v3.0": 3}
"""codebase_version -> layout major version, for every version :func:`load_lerobot` reads"""
DEFAULT_CHUNK_SIZE = 1000
DEFAULT_DATA_FILE_SIZE_IN_MB = 100
DEFAULT_VIDEO_FILE_SIZE_IN_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
LEGACY_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
IMAGE_NAMES = {"hwc": ["height", "width", "channels"], "chw": ["channels", "height", "width"]}
DATASET_ENTRIES = frozenset(
    {"meta", "data", "videos", "images", "README.md", ".gitattributes", ".cache"}
)
"""what the top level of a LeRobot dataset directory holds (a hub download adds the last three)"""
SIDECAR = "meta/imitrl.json"
SIDECAR_FORMAT = "imitrl.lerobot/1"


CAMERA_PREFIX = "observation.images."
"""LeRobot's name for the cameras of a robot: ``observation.images.<camera>``"""


def camera_key(name: str) -> NestedKey:
    """The buffer key a LeRobot camera (video) feature loads into, under ``PIXELS``
    (TorchRL's convention): ``observation.image -> "pixels"``, ``observation.images.<cam>
    -> ("pixels", "<cam>")``, any other ``observation.<x>`` (or ``<x>``) -> ``("pixels",
    "<x>")``; dots inside the camera name become nesting, as for a Dict observation."""
    if name == "observation.image":
        return keys.PIXELS
    camera = name.removeprefix(CAMERA_PREFIX)
    if camera == name:
        camera = name.removeprefix(keys.OBSERVATION + ".")
    return (keys.PIXELS, *camera.split("."))


def feature_name(key: NestedKey) -> str:
    """The LeRobot feature :func:`save_lerobot` writes a buffer key as (``OBSERVATION`` ->
    ``observation.state``, ``EXPERT_ACTION`` -> ``action``, imitrl's own columns, ``PIXELS``
    -> ``observation.image`` and ``("pixels", cam)`` -> ``observation.images.<cam>``
    (:func:`camera_key` backwards), else the dotted key name); ``meta/imitrl.json`` entries
    are checked against it on load."""
    special = {
        keys.OBSERVATION: "observation.state",
        keys.EXPERT_ACTION: "action",
        **{key_name(v): k for k, v in IMITRL_COLUMNS.items()},
        "task_index": "task_index",
        keys.PIXELS: "observation.image",
        keys.ENVIRONMENT_STATE: "observation.environment_state",
    }
    name = special.get(key_name(key), key_name(key))
    if isinstance(key, tuple) and len(key) > 1 and key[0] == keys.PIXELS:
        name = CAMERA_PREFIX + key_name(key[1:])
    if "/" in name:
        raise ValueError(f"LeRobot feature names cannot contain '/': {name!r}")
    return name


# -------------------------------------------------------------------- meta
def read_json(path: Path) -> Any:
    """A JSON metadata file; ValueError naming it when absent or malformed."""
    if not path.is_file():
        raise ValueError(f"{path} not found: not a LeRobot dataset (meta/info.json is required)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err


def _read_jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        raise ValueError(f"{path} not found (a v2.x LeRobot dataset lists its episodes there)")
    out = []
    for i, line in enumerate(path.read_text().splitlines()):
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError as err:
                raise ValueError(f"{path}:{i + 1} is not valid JSON: {err}") from err
    return out


def read_info(root: Path) -> tuple[dict, int]:
    """``meta/info.json``, validated, and its layout's major version (2 or 3)."""
    path = root / "meta" / "info.json"
    info = read_json(path)
    if not isinstance(info, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(info).__name__}")
    for field in ("codebase_version", "fps", "features", "data_path"):
        if field not in info:
            raise ValueError(f"{path}: missing {field!r}")
    fps = info["fps"]
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not math.isfinite(fps):
        raise ValueError(f"{path}: fps must be a number of frames per second, got {fps!r}")
    if fps <= 0:
        raise ValueError(f"{path}: fps must be positive, got {fps!r}")
    if not isinstance(info["data_path"], str):
        raise ValueError(f"{path}: data_path must be a path template, got {info['data_path']!r}")
    major = READ_VERSIONS.get(str(info["codebase_version"]))
    if major is None:
        raise ValueError(
            f"{path}: codebase_version {info['codebase_version']!r} is not supported "
            f"(only {', '.join(READ_VERSIONS)} are)"
        )
    if not isinstance(info["features"], dict):
        raise ValueError(f"{path}: 'features' must map feature names to descriptions")
    for name, ft in info["features"].items():
        _check_feature_name(path, name)
        if not isinstance(ft, dict) or not isinstance(ft.get("dtype"), str):
            raise ValueError(f"{path}: feature {name!r} needs a dtype and a shape, got {ft!r}")
        shape = ft.get("shape")
        if not isinstance(shape, list | tuple) or not all(
            isinstance(d, int) and d >= 0 for d in shape
        ):
            raise ValueError(
                f"{path}: feature {name!r} needs a shape (a list of sizes), got {shape!r}"
            )
    return info, major


def _check_feature_name(path: Path, name: str) -> None:
    """A feature name is a dotted name: LeRobot joins it with ``/`` into the episode
    table's columns (``videos/<feature>/...``, ``stats/<feature>/...``), so ``/`` can be
    none of its characters; nor ``\\``, a NUL or a control character, and it is never
    ``.`` or ``..``: a camera's name becomes a file name (``decode_dir``)."""
    if (
        not name
        or name in (".", "..")
        or any(c in name for c in "/\\")
        or any(ord(c) < 32 for c in name)
    ):
        raise ValueError(
            f"{path}: feature name {name!r} is not a LeRobot feature name (a dotted name "
            "without '/', '\\' or control characters)"
        )


def episode_table(root: Path, info: dict, major: int) -> pa.Table:
    """The episode table in episode order, only the columns a load reads (never the
    statistics): ``episode_index``, ``length``; v3.0 ``data/chunk_index``,
    ``data/file_index``, ``dataset_from_index``/``dataset_to_index`` where a file has them
    (null where another file lacks them) and each camera's ``videos/...``; v2.x ``chunk``.
    Arrow columns: a few numbers per episode, no Python object per episode.

    Checked before anything per episode is built, so that a table declaring more
    episodes than the data holds is refused in a moment: the number of episodes against
    the frames the data files hold (read from their footers; v2.x: against its episode
    files) before the table is read, then every length >= 1 (LeRobot refuses to save an
    empty episode), ``info.json``'s ``total_episodes``, repeated indices. So the episodes,
    and what is built per episode afterwards, never outnumber the frames on disk.
    """
    held = _frames_held(root, major)
    if major == 3:
        table = _episodes_v3(root, held)
    else:
        table = _episodes_v2(root, info, held)
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


def _frames_held(root: Path, major: int) -> int | None:
    """v3.0: the frames in ``data/*/*.parquet``, from the files' footers; v2.x: the
    number of parquet files under ``data/``, one per episode; None if ``data/`` is
    absent (reported where the data is read)."""
    if not (root / "data").is_dir():
        return None
    if major != 3:
        return sum(1 for _ in (root / "data").rglob("*.parquet"))
    return sum(rows_in(f) for f in sorted((root / "data").glob("*/*.parquet")))


def _too_many(root: Path, where: Path, declared: int, held: int | None, of: str) -> None:
    if held is not None and declared > held:
        raise ValueError(
            f"{where}: lists {declared} episodes, the data holds {held} {of}; every episode "
            "holds at least one frame (refused before the table is read)"
        )


def episode_dicts(table: pa.Table) -> list[dict]:
    """Rows of :func:`episode_table` as dicts, one per episode, without the entries its
    file lacked."""
    return [{k: v for k, v in ep.items() if v is not None} for ep in table.to_pylist()]


def data_file(root: Path, info: dict, major: int, ep: dict) -> str:
    """The data file an episode table entry names (``info.json``'s ``data_path``)."""
    if major == 3:
        return fill_template(
            root,
            info,
            "data_path",
            chunk_index=ep["data/chunk_index"],
            file_index=ep["data/file_index"],
        )
    e = ep["episode_index"]
    return fill_template(root, info, "data_path", episode_chunk=ep["chunk"], episode_index=e)


def _episodes_v3(root: Path, held: int | None) -> pa.Table:
    ep_dir = root / "meta" / "episodes"
    files = sorted(ep_dir.glob("*/*.parquet"))
    if not files:
        raise ValueError(
            f"{ep_dir}: no episode metadata files (meta/episodes/chunk-*/file-*.parquet)"
        )
    _too_many(root, ep_dir, sum(rows_in(f) for f in files), held, "frames")
    need = ["episode_index", "length", "data/chunk_index", "data/file_index"]
    optional = ["dataset_from_index", "dataset_to_index"]
    tables = []
    for f in files:
        check_schema(f, None, None)
        names = pq.read_schema(f).names
        missing = [c for c in need if c not in names]
        if missing:
            raise ValueError(f"{f}: episode metadata lacks column(s) {missing}")
        # where each camera's frames lie: videos/<feature>/{chunk_index, file_index,
        # from_timestamp, to_timestamp} (checked where the videos are read)
        cameras = [c for c in names if c.startswith("videos/")]
        columns = need + [c for c in optional if c in names] + cameras
        try:  # not pq.read_table: its pre-buffering reads the statistics columns too
            table = pq.ParquetFile(f, pre_buffer=False).read(columns=columns)
        except (pa.ArrowException, OSError) as err:
            raise ValueError(f"{f}: cannot read the parquet data ({err})") from err
        nulls = [c for c in table.column_names if table.column(c).null_count]
        if nulls:
            raise ValueError(f"{f}: episode metadata column(s) {nulls} hold null entries")
        tables.append(table)
    try:
        table = pa.concat_tables(tables, promote_options="permissive")
    except pa.ArrowException as err:
        raise ValueError(f"{ep_dir}: the episode metadata files disagree ({err})") from err
    return table.sort_by("episode_index").combine_chunks()


def _episodes_v2(root: Path, info: dict, held: int | None) -> pa.Table:
    path = root / "meta" / "episodes.jsonl"
    if path.is_file():
        with open(path, "rb") as f:
            lines = sum(1 for line in f if line.strip())
        _too_many(root, path, lines, held, "episode files")
    episodes = _read_jsonl(path)
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


def fill_template(root: Path, info: dict, field: str, **fields: int | str) -> str:
    """``info.json``'s path template ``field`` (``data_path``, ``video_path``) filled in,
    naming the template when it breaks; a path out of the dataset folder (absolute,
    ``..``, a link out) is refused (:func:`imitrl.fs.contained.inside`)."""
    template = info.get(field)
    if not isinstance(template, str):
        raise ValueError(
            f"{root / 'meta' / 'info.json'}: {field} must be a path template, got {template!r}"
        )
    try:
        filled = template.format(**fields)
    except (KeyError, IndexError, ValueError, AttributeError, TypeError) as err:
        raise ValueError(
            f"{root / 'meta' / 'info.json'}: {field} {template!r} cannot be filled "
            f"with {sorted(fields)} ({type(err).__name__}: {err})"
        ) from err
    inside(root, filled, named_by=f"meta/info.json's {field} {template!r}")
    return filled


def read_tasks(root: Path, major: int) -> list[str]:
    """The task strings, indexed by ``task_index`` (which must run 0..T-1)."""
    pairs = _task_pairs_v2(root) if major == 2 else _task_pairs_v3(root)
    pairs.sort()
    tasks = [t for _, t in pairs]
    if [i for i, _ in pairs] != list(range(len(pairs))):
        raise ValueError(f"{root / 'meta'}: task indices are not 0..{len(pairs) - 1}")
    return tasks


def _task_pairs_v2(root: Path) -> list[tuple[int, str]]:
    path = root / "meta" / "tasks.jsonl"
    rows = _read_jsonl(path)
    for r in rows:
        if not (
            isinstance(r, dict)
            and isinstance(r.get("task_index"), int)
            and isinstance(r.get("task"), str)
        ):
            raise ValueError(f"{path}: entry {r!r} needs an integer 'task_index' and a 'task'")
    return [(r["task_index"], r["task"]) for r in rows]


def _task_pairs_v3(root: Path) -> list[tuple[int, str]]:
    path = root / "meta" / "tasks.parquet"
    table = read_parquet(path)
    pandas_meta = json.loads((table.schema.metadata or {}).get(b"pandas", b"{}"))
    index_cols = [c for c in pandas_meta.get("index_columns", []) if isinstance(c, str)]
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


def rows_in(path: Path) -> int:
    """Frames in a parquet file, from its footer (0 if unreadable: reported when it is read)."""
    try:
        return pq.read_metadata(path).num_rows
    except (pa.ArrowException, OSError):
        return 0
