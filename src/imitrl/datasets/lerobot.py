"""LeRobot datasets as a file format: read v2.1 and v3.0 directories, write v3.0.

No ``lerobot`` package is needed (it cannot be installed beside torch 2.13 and
gymnasium 1.x): the layout is read and written with pyarrow, following
``lerobot/datasets/lerobot_dataset.py`` and ``utils.py`` (lerobot 0.3.x for v2.1,
0.4.x for v3.0).

v3.0 (episodes back to back, many episodes per file)::

    meta/info.json                              codebase_version, fps, features, path templates
    meta/tasks.parquet                          task string (pandas index) -> task_index
    meta/episodes/chunk-000/file-000.parquet    one row per episode: episode_index, tasks, length,
                                                data/chunk_index, data/file_index,
                                                dataset_from_index, dataset_to_index, stats/...
    meta/stats.json                             per-feature min/max/mean/std/count/quantiles
    data/chunk-000/file-000.parquet             frames: features + timestamp, frame_index,
                                                episode_index, index, task_index

v2.1 (one parquet file per episode)::

    meta/info.json, meta/episodes.jsonl, meta/tasks.jsonl, meta/episodes_stats.jsonl
    data/chunk-{episode_index // chunks_size:03d}/episode_{episode_index:06d}.parquet

Column mapping on load (:data:`DEFAULT_KEY_MAP`, extend or override with ``key_map``):
``observation.state -> OBSERVATION``, ``action -> EXPERT_ACTION`` (and ``ACTION``: a
recording is the expert acting), ``next.reward/done/terminated/truncated -> ("next",
...)``, ``task_index -> "task_index"`` (indexes ``LoadedDemonstrations.tasks``; loaded
when there is more than one task); with no ``observation.state`` (nothing mapped to
``OBSERVATION``), every ``observation.<sub>`` feature -> ``("observation", *sub.split("."))``
(a Dict observation); ``episode_index`` gives ``EPISODE`` and ``frame_index`` gives ``STEP``. Rows get round 0
and ``EXPERT_EXECUTED`` True unless the dataset carries imitrl's own columns
(``imitrl.round``, ``imitrl.expert_executed``, ``imitrl.executed_action``,
``imitrl.episode``), which :func:`save_lerobot` writes so that every DAgger round
survives the trip. Image features are decoded (``images="load"``) or skipped with a
warning (``images="skip"``); video features are always skipped with a warning (no
video decoder is a dependency). Nothing is dropped without a warning.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._arrow import (
    column_to_tensor,
    decode_images,
    encode_images,
    hf_feature,
    hf_schema_metadata,
    read_parquet,
    tensor_to_array,
)
from imitrl.datasets._common import (
    NUMPY_NAMES,
    LoadedDemonstrations,
    NestedKey,
    as_key,
    conform_to_env,
    key_name,
    required_rows,
    warn_skipped,
)

__all__ = [
    "DEFAULT_KEY_MAP",
    "IMITRL_COLUMNS",
    "load_lerobot",
    "resolve_lerobot_root",
    "save_lerobot",
]

DEFAULT_KEY_MAP: dict[str, NestedKey] = {
    "observation.state": keys.OBSERVATION,
    "action": keys.EXPERT_ACTION,
    "next.reward": (keys.NEXT, keys.REWARD),
    "next.done": (keys.NEXT, keys.DONE),
    "next.terminated": (keys.NEXT, keys.TERMINATED),
    "next.truncated": (keys.NEXT, keys.TRUNCATED),
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
SIDECAR = "meta/imitrl.json"
SIDECAR_FORMAT = "imitrl.lerobot/1"


# ------------------------------------------------------------------ locate
def resolve_lerobot_root(
    repo_id: str, *, revision: str | None = None, cache_dir: str | Path | None = None
) -> Path:
    """Find a LeRobot dataset already on disk for ``repo_id``, without any network access.

    Looks, in order, in ``$HF_LEROBOT_HOME/<repo_id>`` (LeRobot's default ``root``,
    ``$HF_HOME/lerobot``), then the Hugging Face hub cache
    (``cache_dir`` or ``$HF_HUB_CACHE`` or ``$HF_HOME/hub``):
    ``datasets--<org>--<name>/snapshots/<commit>/`` with ``revision`` (or ``v3.0``,
    ``v2.1``, ``main``) resolved through ``refs/``, else the newest snapshot holding
    ``meta/info.json``.

    Raises:
        ValueError: nothing found (the message lists where it looked).
    """
    hf_home = Path(os.environ.get("HF_HOME", Path.home() / ".cache" / "huggingface"))
    looked: list[str] = []
    if cache_dir is None:
        lerobot_home = Path(os.environ.get("HF_LEROBOT_HOME", hf_home / "lerobot"))
        candidate = lerobot_home / repo_id
        looked.append(str(candidate))
        if (candidate / "meta" / "info.json").is_file():
            return candidate
    hub = Path(cache_dir or os.environ.get("HF_HUB_CACHE", hf_home / "hub"))
    repo_dir = hub / ("datasets--" + repo_id.replace("/", "--"))
    looked.append(str(repo_dir))
    snapshots = repo_dir / "snapshots"
    if snapshots.is_dir():
        refs = [revision] if revision is not None else ["v3.0", "v2.1", "main"]
        for ref in refs:
            ref_file = repo_dir / "refs" / ref
            commit = ref_file.read_text().strip() if ref_file.is_file() else ref
            candidate = snapshots / commit
            if (candidate / "meta" / "info.json").is_file():
                return candidate
        if revision is None:
            found = [p for p in snapshots.iterdir() if (p / "meta" / "info.json").is_file()]
            if found:
                return max(found, key=lambda p: (p / "meta" / "info.json").stat().st_mtime)
    raise ValueError(
        f"no local copy of LeRobot dataset {repo_id!r}"
        + (f" at revision {revision!r}" if revision else "")
        + f" (looked in {looked}); download it first, this loader never uses the network"
    )


def _root(path_or_repo: str | Path, revision: str | None, cache_dir: str | Path | None) -> Path:
    path = Path(path_or_repo)
    if path.is_dir():
        return path
    if isinstance(path_or_repo, str) and re.fullmatch(r"[\w.-]+/[\w.-]+", path_or_repo):
        return resolve_lerobot_root(path_or_repo, revision=revision, cache_dir=cache_dir)
    raise ValueError(f"{path}: no such dataset directory")


def _read_json(path: Path) -> Any:
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


def _info(root: Path) -> tuple[dict, int]:
    path = root / "meta" / "info.json"
    info = _read_json(path)
    for field in ("codebase_version", "fps", "features", "data_path"):
        if field not in info:
            raise ValueError(f"{path}: missing {field!r}")
    major = READ_VERSIONS.get(str(info["codebase_version"]))
    if major is None:
        raise ValueError(
            f"{path}: codebase_version {info['codebase_version']!r} is not supported "
            f"(only {', '.join(READ_VERSIONS)} are)"
        )
    if not isinstance(info["features"], dict):
        raise ValueError(f"{path}: 'features' must map feature names to descriptions")
    for name, ft in info["features"].items():
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


# -------------------------------------------------------------- episodes
def _episodes_v3(root: Path, info: dict) -> list[dict]:
    ep_dir = root / "meta" / "episodes"
    files = sorted(ep_dir.glob("*/*.parquet"))
    if not files:
        raise ValueError(
            f"{ep_dir}: no episode metadata files (meta/episodes/chunk-*/file-*.parquet)"
        )
    need = ["episode_index", "length", "data/chunk_index", "data/file_index"]
    optional = ["dataset_from_index", "dataset_to_index", "tasks"]
    episodes: list[dict] = []
    for f in files:
        table = read_parquet(f)
        missing = [c for c in need if c not in table.column_names]
        if missing:
            raise ValueError(f"{f}: episode metadata lacks column(s) {missing}")
        table = table.select(need + [c for c in optional if c in table.column_names])
        nulls = [c for c in table.column_names if c != "tasks" and table.column(c).null_count]
        if nulls:
            raise ValueError(f"{f}: episode metadata column(s) {nulls} hold null entries")
        episodes.extend(table.to_pylist())
    episodes.sort(key=lambda e: e["episode_index"])
    template = info["data_path"]
    for ep in episodes:
        ep["file"] = template.format(
            chunk_index=ep["data/chunk_index"], file_index=ep["data/file_index"]
        )
    return episodes


def _episodes_v2(root: Path, info: dict) -> list[dict]:
    path = root / "meta" / "episodes.jsonl"
    episodes = _read_jsonl(path)
    for ep in episodes:
        for field in ("episode_index", "length"):
            if not isinstance(ep, dict) or not isinstance(ep.get(field), int):
                raise ValueError(f"{path}: entry {ep!r} has no integer {field!r}")
    episodes.sort(key=lambda e: e["episode_index"])
    chunks = int(info.get("chunks_size", DEFAULT_CHUNK_SIZE))
    template = info["data_path"]
    for ep in episodes:
        ep["file"] = template.format(
            episode_chunk=ep["episode_index"] // chunks, episode_index=ep["episode_index"]
        )
    return episodes


def _tasks(root: Path, major: int) -> list[str]:
    if major == 2:
        path = root / "meta" / "tasks.jsonl"
        rows = _read_jsonl(path)
        for r in rows:
            if not (
                isinstance(r, dict)
                and isinstance(r.get("task_index"), int)
                and isinstance(r.get("task"), str)
            ):
                raise ValueError(f"{path}: entry {r!r} needs an integer 'task_index' and a 'task'")
        pairs = [(r["task_index"], r["task"]) for r in rows]
    else:
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
        pairs = list(zip(table.column("task_index").to_pylist(), strings))
    pairs.sort()
    tasks = [t for _, t in pairs]
    if [i for i, _ in pairs] != list(range(len(pairs))):
        raise ValueError(f"{root / 'meta'}: task indices are not 0..{len(pairs) - 1}")
    return tasks


def _rows_in(path: Path) -> int:
    """Frames in a parquet file, from its footer (0 if unreadable: reported when it is read)."""
    try:
        return pq.read_metadata(path).num_rows
    except (pa.ArrowException, OSError):
        return 0


# ------------------------------------------------------------------- load
def _under_observation(key: NestedKey) -> bool:
    return key == keys.OBSERVATION or (isinstance(key, tuple) and key[0] == keys.OBSERVATION)


def _plan(
    root: Path,
    info: dict,
    key_map: Mapping[str, NestedKey | None] | None,
    images: Literal["skip", "load"],
) -> tuple[dict[str, NestedKey], dict[str, tuple[int, ...]]]:
    """feature -> buffer key, and the exact per-frame shapes recorded by :func:`save_lerobot`.

    Without ``meta/imitrl.json`` and with no feature mapped to ``OBSERVATION`` (no
    ``observation.state``, say), every ``observation.<sub>`` feature maps to the nested key
    ``("observation", *sub.split("."))``: a Dict observation.
    """
    features = info["features"]
    mapping: dict[str, NestedKey | None] = {}
    shapes: dict[str, tuple[int, ...]] = {}
    sidecar = root / SIDECAR
    if sidecar.is_file():
        meta = _read_json(sidecar)
        if meta.get("format") != SIDECAR_FORMAT:
            raise ValueError(f"{sidecar}: unknown format {meta.get('format')!r}")
        for name, entry in meta["columns"].items():
            if name not in features:
                raise ValueError(f"{sidecar}: column {name!r} is not a feature of meta/info.json")
            shapes[name] = tuple(entry["shape"])
            if features[name]["dtype"] != "image" or images == "load":
                mapping[name] = as_key(entry["key"])
    else:
        mapping.update({k: v for k, v in DEFAULT_KEY_MAP.items() if k in features})
        mapping.update({k: v for k, v in IMITRL_COLUMNS.items() if k in features})
    for name, key in (key_map or {}).items():
        if name not in features:
            raise ValueError(
                f"{root / 'meta' / 'info.json'}: key_map names feature {name!r}, which the "
                f"dataset does not declare (features: {sorted(features)})"
            )
        mapping[name] = key
    if not sidecar.is_file() and not any(
        v is not None and _under_observation(v) for v in mapping.values()
    ):
        prefix = keys.OBSERVATION + "."
        for name, ft in features.items():
            loadable = ft["dtype"] not in ("video", "string", "image") or (
                ft["dtype"] == "image" and images == "load"
            )
            if name.startswith(prefix) and name not in mapping and loadable:
                mapping[name] = (keys.OBSERVATION, *name.removeprefix(prefix).split("."))
    plan = {k: v for k, v in mapping.items() if v is not None}
    targets = [key_name(v) for v in plan.values()]
    dup = sorted({t for t in targets if targets.count(t) > 1})
    if dup:
        raise ValueError(f"several features map to the same buffer key(s) {dup}: fix key_map")
    paths = {(v,) if isinstance(v, str) else tuple(v): k for k, v in plan.items()}
    for path, name in paths.items():
        for i in range(1, len(path)):
            if path[:i] in paths:
                raise ValueError(
                    f"{root / 'meta' / 'info.json'}: feature {paths[path[:i]]!r} maps to "
                    f"{key_name(path[:i])!r} and feature {name!r} inside it to "
                    f"{key_name(path)!r}; a key cannot be both a tensor and a group (fix key_map)"
                )
    if not any(_under_observation(v) for v in plan.values()):
        numeric = [k for k, f in features.items() if f["dtype"] not in ("image", "video", "string")]
        raise ValueError(
            f"{root / 'meta' / 'info.json'}: no feature maps to {keys.OBSERVATION!r}; pass "
            f"key_map={{'<feature>': {keys.OBSERVATION!r}}} (features: {numeric})"
        )
    return plan, shapes


def load_lerobot(
    path_or_repo: str | Path,
    *,
    key_map: Mapping[str, NestedKey | None] | None = None,
    images: Literal["skip", "load"] = "skip",
    env: EnvBase | None = None,
    first_episode: int = 0,
    revision: str | None = None,
    cache_dir: str | Path | None = None,
) -> LoadedDemonstrations:
    """Read a local LeRobot dataset (v2.0, v2.1 or v3.0) into demonstration rows.

    Args:
        path_or_repo: the dataset directory, or a ``repo_id`` found in a local Hugging
            Face cache (:func:`resolve_lerobot_root`; never downloads).
        key_map: dataset feature -> buffer key (a str or a nested tuple), merged over
            :data:`DEFAULT_KEY_MAP`; map a feature to None to leave it out on purpose.
        images: ``"load"`` decodes image features into uint8 tensors in the declared
            layout; ``"skip"`` leaves them out with a warning (those :func:`save_lerobot`
            wrote too). Video features are always skipped with a warning.
        env: if given, observation and action shapes must match its specs (else
            ValueError), dtypes are cast where no value changes (within a kind, or
            integer -> floating when exact), reward/done take its shapes, and a missing
            ``terminated``/``truncated`` is derived from ``done``.
        first_episode: added to the episode ids (use ``buffer.next_episode``).
        revision, cache_dir: for resolving a ``repo_id`` (see :func:`resolve_lerobot_root`).

    Returns:
        :class:`LoadedDemonstrations` whose ``rows`` extend a :class:`DemonstrationBuffer`.

    Raises:
        ValueError: missing ``meta/info.json``; a declared feature absent from a data
            file; a truncated or unreadable parquet file; episode lengths or indices that
            contradict the metadata; values that contradict a declared shape; shapes that
            contradict ``env``. The message names the file and the problem, and nothing is
            returned half-loaded.
    """
    if images not in ("skip", "load"):
        raise ValueError(f"images must be 'skip' or 'load', got {images!r}")
    root = _root(path_or_repo, revision, cache_dir)
    info, major = _info(root)
    features: dict[str, dict] = info["features"]
    plan, exact_shapes = _plan(root, info, key_map, images)
    tasks = _tasks(root, major)
    quiet = {"index", "timestamp"}
    if (
        "task_index" in features
        and "task_index" not in plan
        and "task_index" not in (key_map or {})
    ):
        if len(tasks) > 1 and not exact_shapes:
            plan["task_index"] = "task_index"
        else:
            quiet.add("task_index")
    skipped: dict[str, str] = {}
    for name, ft in features.items():
        if name in plan or name in ("episode_index", "frame_index"):
            continue
        if name == "task_index" and name in quiet:
            skipped[name] = (
                f"a single task ({tasks[0]!r})" if len(tasks) == 1 else "not recorded by imitrl"
            )
        elif ft["dtype"] == "video":
            skipped[name] = "video feature (mp4 under videos/): video decoding is not supported"
        elif ft["dtype"] == "string":
            skipped[name] = "string feature: text cannot go into a tensor"
        elif ft["dtype"] == "image" and images == "skip":
            skipped[name] = "image feature not loaded (images='skip'; pass images='load')"
        elif ft["dtype"] == "image":
            plan[name] = name
        elif name in ("index", "timestamp"):
            skipped[name] = "bookkeeping (derivable from episode order and frame_index / fps)"
        elif key_map is not None and name in key_map:
            skipped[name] = "left out by key_map"
            quiet.add(name)  # the caller's choice: listed, not warned about
        else:
            skipped[name] = "no buffer key for it (add it to key_map)"
    for name, key in plan.items():
        if features[name]["dtype"] in ("video", "string"):
            raise ValueError(
                f"{root / 'meta' / 'info.json'}: feature {name!r} has dtype "
                f"{features[name]['dtype']!r}, which cannot be loaded into {key_name(key)!r}"
            )

    episodes = _episodes_v3(root, info) if major == 3 else _episodes_v2(root, info)
    total = info.get("total_episodes")
    if total is not None and total != len(episodes):
        raise ValueError(
            f"{root / 'meta' / 'info.json'} declares {total} episodes, the episode metadata lists "
            f"{len(episodes)}"
        )
    ids = [int(e["episode_index"]) for e in episodes]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{root / 'meta'}: episode indices repeat: {ids}")

    # Frames are read file by file; v3.0 files are concatenated in sorted order, as LeRobot
    # does, and each episode is the slice [dataset_from_index, dataset_to_index) of that
    # concatenation (the episode table's file pointers are not needed, and LeRobot's own
    # aggregate tool leaves them stale: they only name a missing file when frames are
    # missing too); v2.x has one file per episode.
    columns = [*plan, "episode_index", "frame_index"]
    if major == 3:
        files = sorted((root / "data").glob("*/*.parquet"))
        expected = sum(int(ep["length"]) for ep in episodes)
        held = sum(_rows_in(f) for f in files)
        if held < expected:
            absent = [ep["file"] for ep in episodes if not (root / ep["file"]).is_file()]
            if absent:
                eps = [int(ep["episode_index"]) for ep in episodes if ep["file"] == absent[0]]
                raise ValueError(
                    f"{root / absent[0]}: file not found (the episode table places episode(s) "
                    f"{eps} there; the data files hold {held} of {expected} frames)"
                )
        if not files:
            raise ValueError(f"{root / 'data'}: no data files (data/chunk-*/file-*.parquet)")
    else:
        files = [root / ep["file"] for ep in episodes]
    pieces: dict[str, list[torch.Tensor]] = {name: [] for name in plan}
    ep_parts, fi_parts, bounds = [], [], []
    total = 0
    for path in files:
        table = read_parquet(path, columns)
        for name in plan:
            ft = features[name]
            where = f"{path}: feature {name!r}"
            if ft["dtype"] == "image":
                value = decode_images(
                    table.column(name), shape=tuple(ft["shape"]), root=root, where=where
                )
            else:
                value = column_to_tensor(
                    table.column(name), shape=tuple(ft["shape"]), dtype=ft["dtype"], where=where
                )
            pieces[name].append(value)
        for col, parts in (("episode_index", ep_parts), ("frame_index", fi_parts)):
            parts.append(
                column_to_tensor(
                    table.column(col), shape=(1,), dtype="int64", where=f"{path}: {col!r}"
                )
            )
        bounds.append((total, total + table.num_rows, path))
        total += table.num_rows
    all_ep, all_fi = torch.cat(ep_parts), torch.cat(fi_parts)

    def file_at(i: int) -> Path:
        return next((p for s, e, p in bounds if s <= i < e), bounds[-1][2])

    order = []
    for i, ep in enumerate(episodes):
        e, length = int(ep["episode_index"]), int(ep["length"])
        if major == 3 and "dataset_from_index" in ep:
            begin, stop = int(ep["dataset_from_index"]), int(ep["dataset_to_index"])
            if stop - begin != length or begin < 0 or stop > total:
                raise ValueError(
                    f"{root / 'meta' / 'episodes'}: episode {e} spans frames [{begin}, {stop}) "
                    f"with length {length}, the data files hold {total} frames"
                )
            path = file_at(begin)
        elif major == 3:
            hits = torch.nonzero(all_ep == e).flatten()
            begin, stop = (int(hits[0]), int(hits[-1]) + 1) if len(hits) else (0, 0)
            path = file_at(begin)
            if len(hits) != stop - begin:
                raise ValueError(f"{path}: the frames of episode {e} are not contiguous")
        else:
            begin, stop, path = bounds[i]
        if stop - begin != length:
            raise ValueError(
                f"{path}: episode {e} has {stop - begin} frames, the episode metadata says {length}"
            )
        found = all_ep[begin:stop].unique().tolist()
        if found != [e] and length:
            raise ValueError(
                f"{path}: frames [{begin}, {stop}) should hold episode {e}, they hold episode(s) {found}"
            )
        fi = all_fi[begin:stop]
        if length and not bool((fi[1:] > fi[:-1]).all()):
            raise ValueError(f"{path}: frame_index of episode {e} is not increasing")
        order.append(torch.arange(begin, stop))
    index = torch.cat(order)
    frames = len(index)
    if frames == 0:
        raise ValueError(f"{root}: the dataset holds no frames")
    if total != frames or len(index.unique()) != frames:
        raise ValueError(
            f"{root / 'data'}: the data files hold {total} frames, the episode table covers "
            f"{len(index.unique())} of them"
        )
    total_frames = info.get("total_frames")
    if total_frames is not None and total_frames != frames:
        raise ValueError(
            f"{root / 'meta' / 'info.json'} declares {total_frames} frames, the data files hold {frames}"
        )
    pieces = {name: [torch.cat(parts)[index]] for name, parts in pieces.items()}
    episode_ids, steps = [all_ep[index]], [all_fi[index]]

    out: dict[NestedKey, torch.Tensor] = {}
    loaded: dict[str, str] = {}
    for name, key in plan.items():
        value = torch.cat(pieces[name])
        if name in exact_shapes:
            value = value.reshape(value.shape[0], *exact_shapes[name])
        elif key_name(key).startswith(keys.NEXT + ".") and value.ndim == 1:
            value = value.unsqueeze(-1)  # TorchRL keeps reward/done as [..., 1]
        out[key] = value
        loaded[name] = key_name(key)
    if "task_index" in plan and len(tasks):
        bad = out[plan["task_index"]]
        if int(bad.min()) < 0 or int(bad.max()) >= len(tasks):
            raise ValueError(f"{root}: task_index outside the {len(tasks)} tasks of the task table")
    episode = out.pop(keys.EPISODE) if keys.EPISODE in out else torch.cat(episode_ids)
    rows = required_rows(out, episode=episode + int(first_episode), step=torch.cat(steps))
    notes: list[str] = []
    if env is not None:
        names = {v: k for k, v in loaded.items()}
        rows = conform_to_env(
            rows, env, where=str(root / "meta" / "info.json"), notes=notes, names=names
        )
    warn_skipped(root, skipped, quiet=frozenset(quiet))
    return LoadedDemonstrations(
        rows=rows,
        source=root,
        format=f"lerobot {info['codebase_version']}",
        num_episodes=len(episodes),
        tasks=tasks,
        fps=info.get("fps"),
        loaded=loaded,
        skipped=skipped,
        notes=notes,
        metadata=info,
    )


# ------------------------------------------------------------------ save
def _feature_name(key: NestedKey) -> str:
    special = {
        keys.OBSERVATION: "observation.state",
        keys.EXPERT_ACTION: "action",
        **{key_name(v): k for k, v in IMITRL_COLUMNS.items()},
        "task_index": "task_index",
    }
    name = special.get(key_name(key), key_name(key))
    if "/" in name:
        raise ValueError(f"LeRobot feature names cannot contain '/': {name!r}")
    return name


def _stats(values: np.ndarray) -> dict[str, Any]:
    """LeRobot's per-feature statistics (lerobot 0.4 ``compute_stats.get_feature_stats``):
    scalars and vectors over frames; arrays of 2+ dims over every axis but the last, as
    its ``RunningQuantileStats`` reduces them (resuming or merging datasets needs the
    same shapes)."""
    x = values[:, None] if values.ndim == 1 else values.reshape(-1, values.shape[-1])
    xf = x.astype(np.float64)
    shape = (x.shape[-1],)
    out: dict[str, Any] = {
        "min": x.min(axis=0).reshape(shape),
        "max": x.max(axis=0).reshape(shape),
        "mean": xf.mean(axis=0).reshape(shape),
        "std": xf.std(axis=0).reshape(shape),
        "count": np.array([values.shape[0]]),
    }
    for q in QUANTILES:
        out[f"q{round(q * 100):02d}"] = np.quantile(xf, q, axis=0).reshape(shape)
    return out


def _image_layout(name: str, value: torch.Tensor) -> Literal["hwc", "chw"] | None:
    """How a column is written as a LeRobot image feature, or None to write it as an array.

    LeRobot treats every feature whose name contains ``"image"`` as a 3-channel image
    (``compute_stats._validate_stat_value`` wants ``(3, 1, 1)`` stats for it when datasets
    are merged or resumed), so a uint8 ``[N, H, W, 3]`` (or ``[N, 3, H, W]``) column so
    named is written as one; :func:`load_lerobot` with ``images="load"`` gives back the same
    tensor."""
    if "image" not in name or value.dtype != torch.uint8 or value.ndim != 4:
        return None
    if value.shape[-1] == 3:
        return "hwc"
    if value.shape[1] == 3:
        return "chw"
    return None


def _sample_frames(chw: np.ndarray) -> np.ndarray:
    """The frames LeRobot's image statistics read (lerobot 0.4 ``compute_stats.sample_images``):
    ``estimate_num_samples`` of them evenly spaced, each downsampled as
    ``auto_downsample_height_width`` does."""
    n = len(chw)
    k = n if n < 100 else max(100, min(int(n**0.75), 10_000))
    frames = chw[np.round(np.linspace(0, n - 1, k)).astype(int)]
    height, width = frames.shape[2:]
    if max(width, height) >= 300:
        factor = int(width / 150) if width > height else int(height / 150)
        frames = frames[:, :, ::factor, ::factor]
    return frames


def _image_stats(frames: np.ndarray) -> dict[str, Any]:
    """LeRobot's image statistics (``compute_episode_stats``): per channel over the pixels of
    the sampled ``[k, C, H, W]`` frames, scaled to [0, 1], shaped ``(C, 1, 1)``; ``count``
    is the number of frames sampled."""
    channels = frames.shape[1]
    x = frames.transpose(0, 2, 3, 1).reshape(-1, channels).astype(np.float64) / 255.0
    shape = (channels, 1, 1)
    out: dict[str, Any] = {
        "min": x.min(axis=0).reshape(shape),
        "max": x.max(axis=0).reshape(shape),
        "mean": x.mean(axis=0).reshape(shape),
        "std": x.std(axis=0).reshape(shape),
        "count": np.array([len(frames)]),
    }
    for q in QUANTILES:
        out[f"q{round(q * 100):02d}"] = np.quantile(x, q, axis=0).reshape(shape)
    return out


def _feature_names(name: str, value: Any, shape: tuple[int, ...]) -> Any:
    """LeRobot's ``names`` of a feature: None, a list of strings (one per entry of a vector),
    or a mapping to lists of strings (v2.0's ``{"motors": [...]}``)."""
    lists = list(value.values()) if isinstance(value, dict) else [value]
    if value is not None and not all(
        isinstance(v, list) and all(isinstance(x, str) for x in v) for v in lists
    ):
        raise ValueError(
            f"names[{name!r}] must be None, a list of strings or a mapping to lists of "
            f"strings (LeRobot's feature names), got {value!r}"
        )
    if isinstance(value, list) and len(shape) == 1 and len(value) != shape[0]:
        raise ValueError(
            f"names[{name!r}] has {len(value)} entries, the feature has shape {list(shape)}"
        )
    return value


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


def save_lerobot(
    data: DemonstrationBuffer | TensorDictBase,
    path: str | Path,
    *,
    fps: int,
    tasks: str | Sequence[str] = "imitrl demonstrations",
    robot_type: str | None = None,
    episodes_per_file: int | None = None,
    chunks_size: int = DEFAULT_CHUNK_SIZE,
    names: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write demonstrations as a LeRobot v3.0 dataset that LeRobot's own reader opens.

    Every leaf key becomes a feature: ``OBSERVATION -> observation.state``,
    ``EXPERT_ACTION -> action`` (the label a LeRobot policy trains on),
    ``("next", k) -> next.k``, ``ACTION -> imitrl.executed_action``,
    ``EXPERT_EXECUTED -> imitrl.expert_executed``, ``ROUND -> imitrl.round``,
    ``EPISODE -> imitrl.episode`` (LeRobot's ``episode_index`` must run 0..E-1),
    ``STEP -> frame_index``, ``"task_index" -> task_index``; any other key
    ``("a", "b") -> a.b``. A uint8 ``[N, H, W, 3]`` (or ``[N, 3, H, W]``) key whose feature
    name contains ``"image"`` (``observation.images.top``, as ``load_lerobot(...,
    images="load")`` names them) becomes a LeRobot ``image`` feature: PNG frames, names
    ``["height", "width", "channels"]`` (or channels first), per-channel statistics in
    [0, 1] shaped ``(3, 1, 1)`` as LeRobot computes them. ``meta/imitrl.json`` records each
    column's key and exact per-frame shape (LeRobot stores ``[]`` and ``[1]`` alike), so
    :func:`load_lerobot` (with ``images="load"`` for image features) gives back identical
    rows (values, dtypes, shapes, episode boundaries, rounds).

    Args:
        data: a buffer or ``[N]`` rows; each episode one contiguous block whose ``STEP``
            runs 0..length-1 (as :func:`~imitrl.data.rollout_episodes` produces).
        path: the dataset directory (must not exist unless ``overwrite``).
        fps: frames per second (``timestamp = frame_index / fps``).
        tasks: the task of every frame, or the task strings a ``"task_index"`` key indexes.
        robot_type: written to ``info.json``.
        episodes_per_file: episodes per data file (None: all in one file); files roll
            over into ``chunk-001`` ... after ``chunks_size`` files.
        chunks_size: files per chunk directory (LeRobot's ``chunks_size``).
        names: feature -> LeRobot ``names`` for ``info.json`` (None, a list with one string
            per entry of a vector, or a mapping to such lists); to keep a source dataset's,
            pass ``{f: ft["names"] for f, ft in loaded.metadata["features"].items()}``.
            Entries for features not written (bookkeeping, videos, skipped features) are
            ignored; image features always get their layout's names. Default: None for all.
        overwrite: replace an existing directory.

    Returns:
        the dataset directory.
    """
    rows = data.data if isinstance(data, DemonstrationBuffer) else data
    if not isinstance(rows, TensorDictBase) or rows.batch_dims != 1 or rows.shape[0] == 0:
        raise ValueError("save_lerobot needs a non-empty buffer or a TensorDict of rows [N]")
    for k in (keys.OBSERVATION, keys.EPISODE, keys.STEP):
        if k not in rows.keys():
            raise ValueError(f"rows need {k!r} to be written as a LeRobot dataset")
    if keys.EXPERT_ACTION not in rows.keys() and keys.ACTION not in rows.keys():
        raise ValueError(f"rows need {keys.EXPERT_ACTION!r} (or {keys.ACTION!r})")
    if int(fps) != fps or fps <= 0:
        raise ValueError(f"fps must be a positive integer, got {fps!r}")
    if episodes_per_file is not None and episodes_per_file < 1:
        raise ValueError(f"episodes_per_file must be >= 1, got {episodes_per_file}")
    if chunks_size < 1:
        raise ValueError(f"chunks_size must be >= 1, got {chunks_size}")
    rows = rows.cpu()
    path = Path(path)
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists; pass overwrite=True to replace it")

    # episodes: contiguous blocks, STEP = 0..len-1
    episode = rows.get(keys.EPISODE)
    step = rows.get(keys.STEP)
    change = torch.ones(len(episode), dtype=torch.bool)
    change[1:] = episode[1:] != episode[:-1]
    starts = torch.nonzero(change).flatten().tolist()
    ends = [*starts[1:], len(episode)]
    ids = episode[starts].tolist()
    if len(set(ids)) != len(ids):
        raise ValueError(
            "each episode must be one contiguous block of rows (an id reappears later)"
        )
    for s, e in zip(starts, ends):
        if not torch.equal(step[s:e], torch.arange(e - s)):
            raise ValueError(
                f"episode {int(episode[s])}: {keys.STEP!r} must run 0..{e - s - 1} "
                "(LeRobot's frame_index), got " + str(step[s:e].tolist()[:5]) + "..."
            )
    n_frames = len(episode)
    lengths = [e - s for s, e in zip(starts, ends)]

    # tasks
    task_list = [tasks] if isinstance(tasks, str) else list(tasks)
    if not task_list or len(set(task_list)) != len(task_list):
        raise ValueError(f"tasks must be distinct strings, got {task_list!r}")
    if "task_index" in rows.keys():
        task_index = rows.get("task_index").reshape(n_frames).to(torch.int64)
        if int(task_index.min()) < 0 or int(task_index.max()) >= len(task_list):
            raise ValueError(f"'task_index' holds indices outside the {len(task_list)} tasks given")
    else:
        if len(task_list) != 1:
            raise ValueError("several tasks given but the rows have no 'task_index' key")
        task_index = torch.zeros(n_frames, dtype=torch.int64)

    # features
    names = dict(names or {})
    frame_index = step.numpy().astype(np.int64)
    columns: dict[str, pa.Array] = {}
    feature_info: dict[str, dict] = {}
    sidecar: dict[str, dict] = {}
    arrays: dict[str, np.ndarray] = {}
    images: dict[str, np.ndarray] = {}
    for key in rows.keys(include_nested=True, leaves_only=True):
        if key_name(key) in (keys.STEP, "task_index"):
            continue
        value = rows.get(key)
        if value.dtype not in NUMPY_NAMES:
            raise ValueError(f"{key_name(key)!r}: dtype {value.dtype} has no LeRobot equivalent")
        name = _feature_name(key)
        if name in BOOKKEEPING:
            raise ValueError(f"{key_name(key)!r} would overwrite LeRobot's {name!r} column")
        sidecar[name] = {
            "key": list(key) if isinstance(key, tuple) else key,
            "shape": list(value.shape[1:]),
        }
        layout = _image_layout(name, value)
        if layout is not None:  # LeRobot's image feature: PNG frames, per-channel stats
            pixels = value.numpy() if layout == "hwc" else value.numpy().transpose(0, 2, 3, 1)
            columns[name] = encode_images(pixels, frame_index)
            images[name] = pixels.transpose(0, 3, 1, 2)  # (C, H, W), as LeRobot's stats read them
            shape = tuple(value.shape[1:])
            feature_info[name] = {
                "dtype": "image",
                "shape": list(shape),
                "names": IMAGE_NAMES[layout],
            }
            continue
        arr, shape = tensor_to_array(value)
        columns[name] = arr
        arrays[name] = (
            value.numpy().reshape(n_frames, *shape)
            if shape != (1,)
            else value.numpy().reshape(n_frames)
        )
        feature_info[name] = {
            "dtype": NUMPY_NAMES[value.dtype],
            "shape": list(shape),
            "names": _feature_names(name, names.get(name), shape),
        }
    book = {
        "timestamp": (frame_index / fps).astype(np.float32),
        "frame_index": frame_index,
        "episode_index": np.repeat(np.arange(len(ids), dtype=np.int64), lengths),
        "index": np.arange(n_frames, dtype=np.int64),
        "task_index": task_index.numpy(),
    }
    for name, values in book.items():
        columns[name] = pa.array(values)
        arrays[name] = values
        feature_info[name] = {"dtype": str(values.dtype), "shape": [1], "names": None}
    if "task_index" in rows.keys():
        sidecar["task_index"] = {
            "key": "task_index",
            "shape": list(rows.get("task_index").shape[1:]),
        }
    hf = {name: hf_feature(ft["dtype"], tuple(ft["shape"])) for name, ft in feature_info.items()}
    table = pa.table(columns).replace_schema_metadata(hf_schema_metadata(hf))

    tmp = Path(
        tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent if path.parent.exists() else None)
    )
    try:
        _write_v3(
            tmp,
            table,
            arrays,
            images,
            feature_info,
            sidecar,
            starts,
            lengths,
            task_index,
            task_list,
            fps=int(fps),
            robot_type=robot_type,
            episodes_per_file=episodes_per_file or len(ids),
            chunks_size=chunks_size,
        )
        if path.exists():
            shutil.rmtree(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(tmp), str(path))
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return path


def _write_v3(
    root: Path,
    table: pa.Table,
    arrays: dict[str, np.ndarray],
    images: dict[str, np.ndarray],
    feature_info: dict[str, dict],
    sidecar: dict[str, dict],
    starts: list[int],
    lengths: list[int],
    task_index: torch.Tensor,
    task_list: list[str],
    *,
    fps: int,
    robot_type: str | None,
    episodes_per_file: int,
    chunks_size: int,
) -> None:
    n_eps = len(starts)
    ep_rows: list[dict[str, Any]] = []
    chunk, file = 0, 0
    writer: pq.ParquetWriter | None = None
    for i, (s, n) in enumerate(zip(starts, lengths)):
        if i and i % episodes_per_file == 0:  # next file (lerobot's update_chunk_file_indices)
            writer.close()
            writer = None
            chunk, file = (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)
        if writer is None:
            data_path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
            data_path.parent.mkdir(parents=True, exist_ok=True)
            writer = pq.ParquetWriter(
                data_path, table.schema, compression="snappy", use_dictionary=True
            )
        writer.write_table(table.slice(s, n))  # one row group per episode, as lerobot writes
        ep_tasks = sorted({task_list[t] for t in task_index[s : s + n].tolist()})
        row: dict[str, Any] = {
            "episode_index": i,
            "tasks": ep_tasks,
            "length": n,
            "data/chunk_index": chunk,
            "data/file_index": file,
            "dataset_from_index": s,
            "dataset_to_index": s + n,
        }
        ep_stats = {name: _stats(values[s : s + n]) for name, values in arrays.items()}
        ep_stats.update(
            {name: _image_stats(_sample_frames(chw[s : s + n])) for name, chw in images.items()}
        )
        for name in feature_info:  # in feature order, as LeRobot writes the columns
            for stat, v in ep_stats.get(name, {}).items():
                row[f"stats/{name}/{stat}"] = v.tolist()
        row["meta/episodes/chunk_index"] = 0
        row["meta/episodes/file_index"] = 0
        ep_rows.append(row)
    assert writer is not None
    writer.close()

    ep_path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    ep_path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(ep_rows), ep_path, compression="snappy")

    tasks_table = pa.table(
        {
            "task_index": pa.array(range(len(task_list)), pa.int64()),
            "__index_level_0__": pa.array(task_list, pa.large_string()),
        }
    ).replace_schema_metadata({b"pandas": _pandas_index_metadata(len(task_list))})
    pq.write_table(tasks_table, root / "meta" / "tasks.parquet")

    all_stats = {name: _stats(values) for name, values in arrays.items()}
    for name, chw in images.items():
        samples = [_sample_frames(chw[s : s + n]) for s, n in zip(starts, lengths)]
        all_stats[name] = _image_stats(np.concatenate(samples))
    stats = {
        name: {k: v.tolist() for k, v in all_stats[name].items()}
        for name in feature_info
        if name in all_stats
    }
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": n_eps,
        "total_frames": int(sum(lengths)),
        "total_tasks": len(task_list),
        "chunks_size": chunks_size,
        "data_files_size_in_mb": DEFAULT_DATA_FILE_SIZE_IN_MB,
        "video_files_size_in_mb": DEFAULT_VIDEO_FILE_SIZE_IN_MB,
        "fps": fps,
        "splits": {"train": f"0:{n_eps}"},
        "data_path": DATA_PATH,
        "video_path": None,
        "features": feature_info,
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    (root / SIDECAR).write_text(
        json.dumps({"format": SIDECAR_FORMAT, "columns": sidecar}, indent=2)
    )
