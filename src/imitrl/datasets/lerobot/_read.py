"""Read a LeRobot dataset into demonstration rows (:func:`load_lerobot`).

One load reads one folder, pinned by a descriptor (:class:`~imitrl.fs.reading.OpenedFolder`):
every file is opened inside it (:mod:`~imitrl.datasets.lerobot._files`), and a load that
met a replacement in progress (a writer's exchange) runs again on the folder now in place
(:func:`~imitrl.fs.reading.read_whole`), so that a reader gets one whole dataset, the old
or the new, or ``ReplacedWhileReading``, never an error calling it damaged. The metadata
is read first (:func:`_read_meta`), then the frames (:mod:`~imitrl.datasets.lerobot._frames`,
or streamed into a buffer: :mod:`~imitrl.datasets.lerobot._stream`); camera (video)
features are decoded afterwards, file by file (:mod:`~imitrl.datasets.lerobot._video`).
Everything is checked against the metadata before a row is returned.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._arrow import footer_rows
from imitrl.datasets._common import (
    LoadedDemonstrations,
    NestedKey,
    conform_to_env,
    key_name,
    required_rows,
    warn_skipped,
)
from imitrl.datasets.lerobot._checks import verify_files, warn_edited
from imitrl.datasets.lerobot._episodes import episode_table, read_tasks, v3_data_files
from imitrl.datasets.lerobot._files import holds, read_json
from imitrl.datasets.lerobot._frames import checked_frames, columns_in_order, data_files, timestamps
from imitrl.datasets.lerobot._hub import dataset_root
from imitrl.datasets.lerobot._hub_limits import HubLimits
from imitrl.datasets.lerobot._interventions import RoundOrder, check_dagger_columns, own_episodes
from imitrl.datasets.lerobot._layout import SIDECAR, read_info
from imitrl.datasets.lerobot._plan import plan_features, settle_features
from imitrl.datasets.lerobot._stream import (
    Settings,
    Source,
    check_stream,
    extend_stream,
    locate,
)
from imitrl.datasets.lerobot._video import decode_videos
from imitrl.fs.reading import OpenedFolder, ReplacedWhileReading, read_whole

READ_TRIES = 3
"""loads of a dataset replaced while it was read, before ``ReplacedWhileReading``"""


@dataclass(frozen=True)
class _Request:
    """What the caller of :func:`load_lerobot` asked for."""

    key_map: Mapping[str, NestedKey | None] | None
    images: Literal["skip", "load"]
    videos: Literal["decode", "skip"]
    decode_dir: Path | None
    env: EnvBase | None
    first_episode: int


@dataclass(frozen=True)
class _Meta:
    """What a dataset's ``meta/`` says, checked, and what is loaded of it."""

    info: dict
    major: int
    plan: dict[str, NestedKey]
    """feature (not a camera) -> buffer key"""
    cameras: dict[str, NestedKey]
    """video feature -> buffer key"""
    exact_shapes: dict[str, tuple[int, ...]]
    tasks: list[str]
    skipped: dict[str, str]
    quiet: frozenset[str]
    edits: list[str]
    """what LeRobot rewrote or added since save_lerobot wrote it (:func:`verify_files`)"""

    @property
    def names(self) -> dict[str, str]:
        """buffer key name -> the feature it is loaded from"""
        return {key_name(k): name for name, k in {**self.plan, **self.cameras}.items()}


def _read_meta(folder: OpenedFolder, req: _Request) -> _Meta:
    """``meta/``: the checksums ``save_lerobot`` recorded (every file as it was written, but
    for LeRobot's own edits), ``info.json``, the plan of features and the tasks."""
    root = folder.root
    sidecar = read_json(folder, SIDECAR) if holds(folder, SIDECAR) else None
    edits = verify_files(folder, sidecar) if sidecar is not None else []
    info, major = read_info(folder)
    features: dict[str, dict] = info["features"]
    plan, exact_shapes = plan_features(root, info, req.key_map, req.images, req.videos, sidecar)
    tasks = read_tasks(folder, major)
    plan, skipped, quiet = settle_features(
        root, features, plan, exact_shapes, tasks, req.key_map, req.images, req.videos
    )
    cameras = {k: v for k, v in plan.items() if features[k]["dtype"] == "video"}
    plan = {k: v for k, v in plan.items() if k not in cameras}
    return _Meta(info, major, plan, cameras, exact_shapes, tasks, skipped, frozenset(quiet), edits)


def _result(
    root: Path, meta: _Meta, rows, episodes: int, loaded: dict, notes: list[str]
) -> LoadedDemonstrations:
    return LoadedDemonstrations(
        rows=rows,
        source=root,
        format=f"lerobot {meta.info['codebase_version']}",
        num_episodes=episodes,
        tasks=meta.tasks,
        fps=meta.info.get("fps"),
        loaded=loaded,
        skipped=meta.skipped,
        notes=notes,
        metadata=meta.info,
    )


def _load(folder: OpenedFolder, req: _Request) -> tuple[LoadedDemonstrations, _Meta]:
    """The whole dataset in memory (or decoded frames in ``decode_dir``), checked."""
    root = folder.root
    meta = _read_meta(folder, req)
    info = meta.info
    episodes, frames, index = checked_frames(folder, info, meta.major, meta.plan, len(meta.tasks))
    out, loaded = columns_in_order(root, meta.plan, frames, index, meta.exact_shapes)
    check_dagger_columns(
        out,
        frames.episode_index[index],
        frames.frame_index[index],
        lambda i: frames.file_at(int(index[i])),
        RoundOrder(),
        meta.names.get(key_name(keys.EXPERT_EXECUTED), "intervention"),
    )
    if meta.cameras:
        times = timestamps(frames, index, info["fps"])
        out.update(
            decode_videos(folder, info, meta.major, episodes, meta.cameras, times, req.decode_dir)
        )
        loaded.update({name: key_name(key) for name, key in meta.cameras.items()})
    own_episodes(out, frames.episode_index[index], lambda i: frames.file_at(int(index[i])))
    episode = out.pop(keys.EPISODE) if keys.EPISODE in out else frames.episode_index[index]
    step = frames.frame_index[index]
    rows = required_rows(out, episode=episode, step=step, first_episode=req.first_episode)
    notes: list[str] = []
    if req.env is not None:
        names = {v: k for k, v in loaded.items()}
        where = str(root / "meta" / "info.json")
        rows = conform_to_env(rows, req.env, where=where, notes=notes, names=names)
    return _result(root, meta, rows, len(episodes), loaded, notes), meta


def _source(folder: OpenedFolder, meta: _Meta, req: _Request) -> tuple[Source, Settings]:
    """Where a streamed load finds each episode's frames, checked against the metadata."""
    info, major = meta.info, meta.major
    v3_files = v3_data_files(folder) if major == 3 else None
    table = episode_table(folder, info, major, v3_files)
    if not table.num_rows:
        raise ValueError(f"{folder.root / 'meta'}: the dataset has no episodes (nothing to load)")
    files, named_by = data_files(folder, info, major, table, v3_files)
    if v3_files is not None:
        counts = [v3_files[f] for f in files]
    else:
        counts = [footer_rows(folder, f, named_by=named_by) for f in files]
    src = locate(folder, info, major, table, files, counts, named_by)
    settings = Settings(
        meta.plan,
        meta.cameras,
        meta.exact_shapes,
        len(meta.tasks),
        req.first_episode,
        req.env,
        meta.names,
    )
    return src, settings


def _load_into(
    root: Path, into: DemonstrationBuffer, req: _Request
) -> tuple[LoadedDemonstrations, _Meta]:
    """``load_lerobot(..., into=buffer)``: every piece checked (pass 1), then added (pass 2).

    Pass 1 runs again on a folder replaced while it ran, as :func:`read_whole` runs a load
    again; pass 2 runs once, on the folder pass 1 checked (run again after some pieces
    were added, it would add them twice)."""
    for _ in range(READ_TRIES):
        with OpenedFolder(root, what="dataset") as folder:
            try:
                meta = _read_meta(folder, req)
                src, settings = _source(folder, meta, req)
                notes = check_stream(into, src, settings)
            except ValueError:
                if not folder.replaced():
                    raise
                continue
            rows = extend_stream(into, src, settings)
            loaded = {v: k for k, v in meta.names.items()}
            return _result(root, meta, rows, src.episodes.num_rows, loaded, notes), meta
    raise ReplacedWhileReading(
        f"{root}: the dataset was replaced while it was read, {READ_TRIES} times in a row; "
        "try again when its writer has finished"
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
    hub_limits: HubLimits | None = None,
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
        hub_limits: the download's timeouts, deadlines, size bounds and redirect hosts
            (:class:`~imitrl.datasets.lerobot.HubLimits`; None: its defaults, with
            ``HF_HUB_DOWNLOAD_TIMEOUT`` read).
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
            of its episodes' timestamps; a file that is not a regular file inside the folder
            (a symbolic link out, a FIFO), metadata past its size bound
            (:data:`~imitrl.datasets.lerobot._files.READ_LIMITS`) or nested too deep, a path
            template asking for a huge format width, an image whose header declares more
            pixels than :data:`~imitrl.datasets._arrow.MAX_IMAGE_PIXELS` or than its bytes
            can hold. The message names the file and the problem, and nothing is returned
            half-loaded. A dataset replaced while it is read (``save_lerobot(...,
            overwrite=True)`` by another process) is read again, whole
            (:func:`~imitrl.fs.reading.read_whole`); ``ReplacedWhileReading`` (a ValueError)
            when it was replaced during every try.
        ImportError: a video to decode and no PyAV (``pip install 'imitrl[datasets]'``); a
            ``repo_id`` to download and no huggingface_hub (``pip install 'imitrl[hub]'``).
    """
    if images not in ("skip", "load"):
        raise ValueError(f"images must be 'skip' or 'load', got {images!r}")
    if videos not in ("decode", "skip"):
        raise ValueError(f"videos must be 'decode' or 'skip', got {videos!r}")
    if into is not None and decode_dir is not None:
        raise ValueError("decode_dir is for a load into memory; with into= frames go to the buffer")
    root = dataset_root(path_or_repo, revision, cache_dir, limits=hub_limits)
    where = None if decode_dir is None else Path(decode_dir)
    req = _Request(key_map, images, videos, where, env, first_episode)
    if into is not None:
        loaded, meta = _load_into(root, into, req)
    else:
        loaded, meta = read_whole(
            root, lambda folder: _load(folder, req), what="dataset", tries=READ_TRIES
        )
    warn_skipped(root, meta.skipped, quiet=meta.quiet)
    warn_edited(root, meta.edits, meta.info["features"])
    return loaded
