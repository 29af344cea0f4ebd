"""Build LeRobot dataset directories by hand with pyarrow, laid out as lerobot itself writes them.

v2.1 follows lerobot 0.3.3 (``LeRobotDataset.create`` + ``add_frame`` + ``save_episode``):
one parquet file per episode with ``fixed_size_list`` vectors and the Hugging Face
``datasets`` schema metadata (``"_type": "Sequence"``), ``meta/episodes.jsonl``,
``meta/tasks.jsonl``, ``meta/episodes_stats.jsonl``. v3.0 follows lerobot 0.4.4: data
files holding many episodes back to back (one row group per episode), the episode
table ``meta/episodes/chunk-*/file-*.parquet`` and ``meta/tasks.parquet`` with the task
strings as the pandas index. Both layouts were checked byte-for-byte in structure
against files written by the real tools.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

FPS = 50


def episodes_data(lengths, *, seed=0, obs_dim=4, image=None):
    """Per-episode numpy columns: observation.state float32 [T, obs_dim], action int64 [T],
    next.reward float32 [T], next.done bool [T], task_index, optional uint8 images [T, H, W, 3]."""
    rng = np.random.default_rng(seed)
    out = []
    for e, n in enumerate(lengths):
        ep = {
            "observation.state": rng.standard_normal((n, obs_dim)).astype(np.float32),
            "action": rng.integers(0, 2, n).astype(np.int64),
            "next.reward": np.ones(n, dtype=np.float32),
            "next.done": np.arange(n) == n - 1,
            "task_index": np.full(n, e % 2, dtype=np.int64),
        }
        if image is not None:
            ep["observation.images.cam"] = rng.integers(0, 255, (n, *image, 3), dtype=np.uint8)
        out.append(ep)
    return out


TASKS = ["balance the pole", "swing it up"]


def _features(obs_dim: int, image) -> dict:
    f = {
        "observation.state": {"dtype": "float32", "shape": [obs_dim], "names": None},
        "action": {"dtype": "int64", "shape": [1], "names": None},
        "next.reward": {"dtype": "float32", "shape": [1], "names": None},
        "next.done": {"dtype": "bool", "shape": [1], "names": None},
    }
    if image is not None:
        f["observation.images.cam"] = {
            "dtype": "image",
            "shape": [*image, 3],
            "names": ["height", "width", "channels"],
        }
    for name, dtype in [
        ("timestamp", "float32"),
        ("frame_index", "int64"),
        ("episode_index", "int64"),
        ("index", "int64"),
        ("task_index", "int64"),
    ]:
        f[name] = {"dtype": dtype, "shape": [1], "names": None}
    return f


def _png(pixels: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


def _table(ep: dict, e: int, start: int, obs_dim: int, hf_list_type: str, vector_layout: str):
    n = len(ep["action"])
    flat = pa.array(ep["observation.state"].reshape(-1))
    if vector_layout == "fixed":
        obs = pa.FixedSizeListArray.from_arrays(flat, obs_dim)
    else:  # variable-length lists, as lerobot's v2.1 -> v3.0 converter writes them
        obs = pa.ListArray.from_arrays(
            pa.array(np.arange(0, n * obs_dim + 1, obs_dim, dtype=np.int32)), flat
        )
    cols = {
        "observation.state": obs,
        "action": pa.array(ep["action"]),
        "next.reward": pa.array(ep["next.reward"]),
        "next.done": pa.array(ep["next.done"]),
    }
    hf = {
        "observation.state": {
            "feature": {"dtype": "float32", "_type": "Value"},
            "length": obs_dim,
            "_type": hf_list_type,
        },
        "action": {"dtype": "int64", "_type": "Value"},
        "next.reward": {"dtype": "float32", "_type": "Value"},
        "next.done": {"dtype": "bool", "_type": "Value"},
    }
    if "observation.images.cam" in ep:
        cols["observation.images.cam"] = pa.array(
            [
                {"bytes": _png(img), "path": f"frame_{i:06d}.png"}
                for i, img in enumerate(ep["observation.images.cam"])
            ],
            pa.struct([("bytes", pa.binary()), ("path", pa.string())]),
        )
        hf["observation.images.cam"] = {"_type": "Image"}
    cols.update(
        {
            "timestamp": pa.array((np.arange(n) / FPS).astype(np.float32)),
            "frame_index": pa.array(np.arange(n, dtype=np.int64)),
            "episode_index": pa.array(np.full(n, e, dtype=np.int64)),
            "index": pa.array(np.arange(start, start + n, dtype=np.int64)),
            "task_index": pa.array(ep["task_index"]),
        }
    )
    for name, dtype in [
        ("timestamp", "float32"),
        ("frame_index", "int64"),
        ("episode_index", "int64"),
        ("index", "int64"),
        ("task_index", "int64"),
    ]:
        hf[name] = {"dtype": dtype, "_type": "Value"}
    meta = {b"huggingface": json.dumps({"info": {"features": hf}}).encode()}
    return pa.table(cols).replace_schema_metadata(meta)


def _stats(ep: dict) -> dict:
    out = {}
    for k, v in ep.items():
        if k == "observation.images.cam":
            continue
        x = v.reshape(len(v), -1)
        out[k] = {
            "min": x.min(0).tolist(),
            "max": x.max(0).tolist(),
            "mean": x.astype(float).mean(0).tolist(),
            "std": x.astype(float).std(0).tolist(),
            "count": [len(v)],
        }
    return out


def write_v21(root: Path, episodes: list[dict], *, chunks_size: int = 1000, image=None) -> Path:
    """A v2.1 dataset as lerobot 0.3.3 writes it."""
    obs_dim = episodes[0]["observation.state"].shape[1]
    (root / "meta").mkdir(parents=True)
    start = 0
    ep_lines, stat_lines = [], []
    for e, ep in enumerate(episodes):
        n = len(ep["action"])
        path = root / f"data/chunk-{e // chunks_size:03d}/episode_{e:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(_table(ep, e, start, obs_dim, "Sequence", "fixed"), path)
        tasks = sorted({TASKS[t] for t in ep["task_index"].tolist()})
        ep_lines.append(json.dumps({"episode_index": e, "tasks": tasks, "length": n}))
        stat_lines.append(json.dumps({"episode_index": e, "stats": _stats(ep)}))
        start += n
    (root / "meta" / "episodes.jsonl").write_text("\n".join(ep_lines) + "\n")
    (root / "meta" / "episodes_stats.jsonl").write_text("\n".join(stat_lines) + "\n")
    (root / "meta" / "tasks.jsonl").write_text(
        "\n".join(json.dumps({"task_index": i, "task": t}) for i, t in enumerate(TASKS)) + "\n"
    )
    info = {
        "codebase_version": "v2.1",
        "robot_type": None,
        "total_episodes": len(episodes),
        "total_frames": start,
        "total_tasks": len(TASKS),
        "total_videos": 0,
        "total_chunks": (len(episodes) - 1) // chunks_size + 1,
        "chunks_size": chunks_size,
        "fps": FPS,
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": None,
        "features": _features(obs_dim, image),
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return root


def write_v30(
    root: Path,
    episodes: list[dict],
    *,
    files: list[tuple[int, int]],
    meta_files: int = 1,
    vector_layout: str = "fixed",
    image=None,
) -> Path:
    """A v3.0 dataset as lerobot 0.4.4 writes it; ``files[e] = (chunk, file)`` of episode e,
    the episode table split over ``meta_files`` files."""
    obs_dim = episodes[0]["observation.state"].shape[1]
    groups: dict[tuple[int, int], list] = {}
    start = 0
    rows = []
    for e, ep in enumerate(episodes):
        n = len(ep["action"])
        groups.setdefault(files[e], []).append(_table(ep, e, start, obs_dim, "List", vector_layout))
        rows.append(
            {
                "episode_index": e,
                "tasks": sorted({TASKS[t] for t in ep["task_index"].tolist()}),
                "length": n,
                "data/chunk_index": files[e][0],
                "data/file_index": files[e][1],
                "dataset_from_index": start,
                "dataset_to_index": start + n,
                "stats/action/count": [n],
                "meta/episodes/chunk_index": 0,
                "meta/episodes/file_index": 0,
            }
        )
        start += n
    for (c, f), tables in groups.items():
        path = root / f"data/chunk-{c:03d}/file-{f:03d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        with pq.ParquetWriter(path, tables[0].schema) as w:
            for t in tables:
                w.write_table(t)  # one row group per episode
    per = -(-len(rows) // meta_files)
    for i in range(meta_files):
        part = rows[i * per : (i + 1) * per]
        for r in part:
            r["meta/episodes/file_index"] = i
        path = root / f"meta/episodes/chunk-000/file-{i:03d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(part), path)
    tasks = pa.table(
        {
            "task_index": pa.array(range(len(TASKS)), pa.int64()),
            "__index_level_0__": pa.array(TASKS, pa.large_string()),
        }
    )
    pandas_meta = {"index_columns": ["__index_level_0__"], "columns": []}
    pq.write_table(
        tasks.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()}),
        root / "meta/tasks.parquet",
    )
    info = {
        "codebase_version": "v3.0",
        "robot_type": None,
        "total_episodes": len(episodes),
        "total_frames": start,
        "total_tasks": len(TASKS),
        "chunks_size": 1000,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200,
        "fps": FPS,
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": None,
        "features": _features(obs_dim, image),
    }
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    return root
