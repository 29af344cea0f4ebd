"""Read a LeRobot dataset's frames into demonstration rows (:func:`load_lerobot`).

Frames are read file by file; v3.0 files are concatenated in sorted order, as LeRobot
does, and each episode is the slice ``[dataset_from_index, dataset_to_index)`` of that
concatenation (the episode table's file pointers are not needed, and LeRobot's own
aggregate tool leaves them stale: they only name a missing file when frames are
missing too); v2.x has one file per episode. Camera (video) features are decoded
afterwards, file by file (:mod:`~imitrl.datasets.lerobot._video`). Everything is checked
against the metadata before a row is returned.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pyarrow as pa
import torch
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._arrow import column_to_tensor, decode_images, read_parquet
from imitrl.datasets._common import (
    LoadedDemonstrations,
    NestedKey,
    conform_to_env,
    key_name,
    required_rows,
    warn_skipped,
)
from imitrl.datasets.lerobot._checks import check_frames, verify_files, warn_edited
from imitrl.datasets.lerobot._hub import dataset_root
from imitrl.datasets.lerobot._layout import (
    SIDECAR,
    data_file,
    episode_dicts,
    episode_table,
    read_info,
    read_json,
    read_tasks,
    rows_in,
)
from imitrl.datasets.lerobot._plan import plan_features, settle_features
from imitrl.datasets.lerobot._stream import Settings, locate, stream_into
from imitrl.datasets.lerobot._video import decode_videos


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


def _data_files(root: Path, info: dict, major: int, table: pa.Table) -> list[Path]:
    """The data files to read, in order: v3.0's sorted ``data/*/*.parquet`` (a missing
    file the episode table names is reported when frames are missing), v2.x's one per
    episode (``table``: :func:`~imitrl.datasets.lerobot._layout.episode_table`)."""
    if major != 3:
        return [root / data_file(root, info, major, ep) for ep in episode_dicts(table)]
    files = sorted((root / "data").glob("*/*.parquet"))
    expected = int(table.column("length").to_numpy().sum())
    held = sum(rows_in(f) for f in files)
    if held < expected:
        places = table.select(["episode_index", "data/chunk_index", "data/file_index"])
        episodes = places.to_pylist()
        named = [data_file(root, info, major, ep) for ep in episodes]
        absent = [f for f in named if not (root / f).is_file()]
        if absent:
            eps = [int(ep["episode_index"]) for ep, f in zip(episodes, named) if f == absent[0]]
            raise ValueError(
                f"{root / absent[0]}: file not found (the episode table places episode(s) "
                f"{eps} there; the data files hold {held} of {expected} frames)"
            )
    if not files:
        raise ValueError(f"{root / 'data'}: no data files (data/chunk-*/file-*.parquet)")
    return files


def _read_frames(
    root: Path, files: list[Path], plan: Mapping[str, NestedKey], features: dict[str, dict]
) -> _Frames:
    """The planned features and the bookkeeping columns of every file, as tensors."""
    book_names = ["episode_index", "frame_index"]
    book_names += [c for c in ("timestamp", "task_index") if c in features]
    columns: dict[str, list[torch.Tensor]] = {name: [] for name in plan}
    book: dict[str, list[torch.Tensor]] = {name: [] for name in book_names}
    bounds = []
    total = 0
    declared = [name for name, ft in features.items() if ft["dtype"] != "video"]
    for path in files:
        table = read_parquet(path, list(dict.fromkeys([*plan, *book_names])), declared=declared)
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
            columns[name].append(value)
        for name in book_names:
            dtype = "float64" if name == "timestamp" else "int64"
            book[name].append(
                column_to_tensor(
                    table.column(name), shape=(1,), dtype=dtype, where=f"{path}: {name!r}"
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
    total_frames = info.get("total_frames")
    if total_frames is not None and total_frames != n:
        raise ValueError(
            f"{root / 'meta' / 'info.json'} declares {total_frames} frames, the data files hold {n}"
        )
    return index


def _columns(
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


def _checked_frames(
    root: Path, info: dict, major: int, plan: Mapping[str, NestedKey], n_tasks: int
) -> tuple[list[dict], _Frames, torch.Tensor]:
    """The episode table, the frames, and ``[N]`` the frames' order, once the frames agree
    with the episode table and with LeRobot's bookkeeping (``frame_index``, ``timestamp``,
    ``task_index``: :func:`~imitrl.datasets.lerobot._checks.check_frames`)."""
    table = episode_table(root, info, major)
    if not table.num_rows:
        raise ValueError(f"{root / 'meta'}: the dataset has no episodes (nothing to load)")
    episodes = episode_dicts(table)
    frames = _read_frames(root, _data_files(root, info, major, table), plan, info["features"])
    index = _frame_order(root, info, episodes, major, frames)
    step = torch.cat([torch.arange(int(ep["length"])) for ep in episodes])
    book = {k: v[index] for k, v in frames.book.items() if k != "episode_index"}

    def file_of(i: int) -> Path:
        return frames.file_at(int(index[i]))

    check_frames(frames.episode_index[index], step, book, file_of, info["fps"], n_tasks)
    return episodes, frames, index


def _timestamps(frames: _Frames, index: torch.Tensor, fps: float) -> torch.Tensor:
    """``[N]`` float64 each row's ``timestamp`` in its episode (``frame_index / fps`` where the
    dataset has no ``timestamp`` column): where its camera frames lie in the videos."""
    if "timestamp" in frames.book:
        return frames.book["timestamp"][index].double()
    return frames.frame_index[index].double() / fps


def _names(plan: Mapping[str, NestedKey], cameras: Mapping[str, NestedKey]) -> dict[str, str]:
    """buffer key name -> the feature it is loaded from"""
    return {key_name(k): name for name, k in {**plan, **cameras}.items()}


def _stream(
    into: DemonstrationBuffer,
    root: Path,
    info: dict,
    major: int,
    settings: Settings,
    tasks: list[str],
    skipped: dict[str, str],
    quiet: set[str],
) -> LoadedDemonstrations:
    """``load_lerobot(..., into=buffer)``: checked, then streamed into the buffer."""
    table = episode_table(root, info, major)
    if not table.num_rows:
        raise ValueError(f"{root / 'meta'}: the dataset has no episodes (nothing to load)")
    src = locate(root, info, major, table, _data_files(root, info, major, table))
    rows, notes = stream_into(into, src, settings)
    warn_skipped(root, skipped, quiet=frozenset(quiet))
    return LoadedDemonstrations(
        rows=rows,
        source=root,
        format=f"lerobot {info['codebase_version']}",
        num_episodes=table.num_rows,
        tasks=tasks,
        fps=info.get("fps"),
        loaded={v: k for k, v in settings.names.items()},
        skipped=skipped,
        notes=notes,
        metadata=info,
    )


def load_lerobot(
    path_or_repo: str | Path,
    *,
    key_map: Mapping[str, NestedKey | None] | None = None,
    images: Literal["skip", "load"] = "skip",
    videos: Literal["decode", "skip"] = "decode",
    decode_dir: str | Path | None = None,
    env: EnvBase | None = None,
    first_episode: int = 0,
    revision: str | None = None,
    cache_dir: str | Path | None = None,
    into: DemonstrationBuffer | None = None,
) -> LoadedDemonstrations:
    """Read a local LeRobot dataset (v2.0, v2.1 or v3.0) into demonstration rows.

    Args:
        path_or_repo: the dataset directory, or a ``repo_id`` (``<org>/<name>``) found in
            the local caches (:func:`resolve_lerobot_root`) or, when none holds it and
            ``HF_HUB_OFFLINE`` is not set, downloaded from the Hub into
            ``$HF_LEROBOT_HOME/hub`` as lerobot 0.6 does (:func:`download_lerobot`; needs
            ``pip install 'imitrl[hub]'``).
        key_map: dataset feature -> buffer key (a str or a nested tuple), merged over
            :data:`DEFAULT_KEY_MAP`; map a feature to None to leave it out on purpose.
        images: ``"load"`` decodes image features into uint8 tensors in the declared
            layout; ``"skip"`` leaves them out with a warning (those :func:`save_lerobot`
            wrote too).
        videos: ``"decode"`` decodes every video (camera) feature with PyAV into uint8
            ``[N, H, W, 3]`` under ``PIXELS``: ``observation.image -> "pixels"``,
            ``observation.images.<cam> -> ("pixels", "<cam>")``, any other
            ``observation.<x> -> ("pixels", "<x>")`` (``key_map`` overrides or drops
            them), frame ``t`` being the video frame at its timestamp within LeRobot's
            tolerance (1e-4 s); ``"skip"`` leaves them out with a warning.
        decode_dir: where decoded frames go: each video feature into the memory-mapped
            file ``<decode_dir>/<feature>.uint8`` (a tensordict ``MemoryMappedTensor``,
            replaced if present), so that a large dataset's frames stay on disk instead of
            in resident memory; None decodes into ordinary tensors.
        env: if given, observation and action shapes must match its specs (else
            ValueError), dtypes are cast where no value changes (within a kind, or
            integer -> floating when exact), reward/done take its shapes, and a missing
            ``terminated``/``truncated`` is derived from ``done`` (an episode that ends at
            the env's time limit is truncated; recorded flags are kept as they are).
        first_episode: added to the episode ids (use ``buffer.next_episode``).
        revision, cache_dir: for resolving or downloading a ``repo_id`` (see
            :func:`resolve_lerobot_root` and :func:`download_lerobot`).
        into: stream the dataset into this buffer (in memory or on disk,
            ``DemonstrationBuffer(path=...)``) a few episodes at a time
            (:mod:`~imitrl.datasets.lerobot._stream`): resident memory does not grow with
            the dataset's length. Every check runs over the whole dataset before the
            buffer is extended (the dataset is read twice), so a bad file anywhere leaves
            the buffer as it was. ``rows`` is then a view of the rows added to the buffer.
            Not with ``decode_dir`` (the frames go to the buffer).

    Returns:
        :class:`LoadedDemonstrations` whose ``rows`` extend a :class:`DemonstrationBuffer`;
        a dataset whose only observation is a camera gives rows with ``PIXELS`` and no
        ``OBSERVATION``.

    Raises:
        ValueError: missing ``meta/info.json``; no episodes; a declared feature absent
            from a data file; a truncated or unreadable parquet file; a file changed since
            :func:`save_lerobot` wrote it other than by LeRobot's own edits in place (it
            rewrites ``meta/info.json``'s totals, ``meta/stats.json``,
            ``meta/tasks.parquet`` and adds files when it resumes recording or recomputes
            statistics: such a dataset loads with a warning saying what of
            ``meta/imitrl.json`` no longer applies); episode lengths or indices that contradict the
            metadata; ``frame_index`` not 0..length-1; timestamps not ``1 / fps`` apart
            (LeRobot's tolerance, 1e-4 s); a ``task_index`` outside the task table; values
            that contradict a declared shape or dtype (no value is ever changed by a cast);
            NaN or inf; shapes that contradict ``env``; a video file missing, unreadable
            (truncated, corrupt), of another size than declared, or without a frame at one
            of its episodes' timestamps. The message names the file and the problem, and
            nothing is returned half-loaded.
        ImportError: a video to decode and no PyAV (``pip install 'imitrl[datasets]'``); a
            ``repo_id`` to download and no huggingface_hub (``pip install 'imitrl[hub]'``).
    """
    if images not in ("skip", "load"):
        raise ValueError(f"images must be 'skip' or 'load', got {images!r}")
    if videos not in ("decode", "skip"):
        raise ValueError(f"videos must be 'decode' or 'skip', got {videos!r}")
    if into is not None and decode_dir is not None:
        raise ValueError("decode_dir is for a load into memory; with into= frames go to the buffer")
    root = dataset_root(path_or_repo, revision, cache_dir)
    edits: list[str] = []
    if (root / SIDECAR).is_file():  # written by save_lerobot: every file as it was written,
        edits = verify_files(root, read_json(root / SIDECAR))  # but for LeRobot's own edits
    info, major = read_info(root)
    features: dict[str, dict] = info["features"]
    plan, exact_shapes = plan_features(root, info, key_map, images, videos)
    tasks = read_tasks(root, major)
    plan, skipped, quiet = settle_features(
        root, features, plan, exact_shapes, tasks, key_map, images, videos
    )
    cameras = {k: v for k, v in plan.items() if features[k]["dtype"] == "video"}
    plan = {k: v for k, v in plan.items() if k not in cameras}
    if into is not None:
        settings = Settings(
            plan, cameras, exact_shapes, len(tasks), first_episode, env, _names(plan, cameras)
        )
        streamed = _stream(into, root, info, major, settings, tasks, skipped, quiet)
        warn_edited(root, edits, features)
        return streamed
    episodes, frames, index = _checked_frames(root, info, major, plan, len(tasks))
    out, loaded = _columns(root, plan, frames, index, exact_shapes)
    if cameras:
        times = _timestamps(frames, index, info["fps"])
        where = None if decode_dir is None else Path(decode_dir)
        out.update(decode_videos(root, info, major, episodes, cameras, times, where))
        loaded.update({name: key_name(key) for name, key in cameras.items()})
    episode = out.pop(keys.EPISODE) if keys.EPISODE in out else frames.episode_index[index]
    rows = required_rows(out, episode=episode + int(first_episode), step=frames.frame_index[index])
    notes: list[str] = []
    if env is not None:
        names = {v: k for k, v in loaded.items()}
        where = str(root / "meta" / "info.json")
        rows = conform_to_env(rows, env, where=where, notes=notes, names=names)
    warn_skipped(root, skipped, quiet=frozenset(quiet))
    warn_edited(root, edits, features)
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
