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
    videos/<camera>/chunk-000/file-000.mp4      a camera's episodes back to back (AV1 by
                                                default); the episode table adds, per camera,
                                                videos/<camera>/{chunk_index, file_index,
                                                from_timestamp, to_timestamp}

v2.1 (one parquet file per episode)::

    meta/info.json, meta/episodes.jsonl, meta/tasks.jsonl, meta/episodes_stats.jsonl
    data/chunk-{episode_index // chunks_size:03d}/episode_{episode_index:06d}.parquet
    videos/chunk-{episode_index // chunks_size:03d}/<camera>/episode_{episode_index:06d}.mp4

Column mapping on load (:data:`DEFAULT_KEY_MAP`, extend or override with ``key_map``):
``observation.state -> OBSERVATION``, ``action -> EXPERT_ACTION`` (and ``ACTION``: a
recording is the expert acting), ``next.reward/done/terminated/truncated -> ("next",
...)``, ``task_index -> "task_index"`` (indexes ``LoadedDemonstrations.tasks``; loaded
when there is more than one task); with no ``observation.state`` (nothing mapped to
``OBSERVATION``), every ``observation.<sub>`` feature but the cameras ->
``("observation", *sub.split("."))`` (a Dict observation); ``episode_index`` gives ``EPISODE`` and ``frame_index`` gives ``STEP``. LeRobot's DAgger column ``intervention`` (its DAgger
strategy's: True on a human's corrections) gives ``EXPERT_EXECUTED``. Rows get round 0
and ``EXPERT_EXECUTED`` True unless the dataset carries these or imitrl's own columns
(``imitrl.round``, ``imitrl.executed_action``, ``imitrl.episode``, ``imitrl.beta``,
``imitrl.policy_version``; ``imitrl.expert_executed``, which imitrl wrote before
``intervention``), which :func:`save_lerobot` writes so that every DAgger round
survives the trip (:func:`save_dagger_lerobot`: a DAgger run's rounds in LeRobot's DAgger
schema; ``_interventions``: what those columns must hold on load). Image features are decoded (``images="load"``, under their own
names) or skipped with a warning (``images="skip"``). Video (camera) features are
decoded with PyAV on CPU (``videos="decode"``, the default; ``videos="skip"`` drops them
with a warning) into uint8 ``[N, H, W, 3]`` under ``PIXELS`` (TorchRL's convention):
``observation.image -> "pixels"``, ``observation.images.<cam> -> ("pixels", "<cam>")``,
any other ``observation.<x> -> ("pixels", "<x>")``; ``key_map`` overrides or drops them.
Frame ``t`` of an episode is the video frame at its ``timestamp`` (v3.0: plus the
episode's ``from_timestamp``) within LeRobot's tolerance, 1e-4 s; ``decode_dir`` puts the
frames in memory-mapped files instead of memory. A dataset whose only observation is a
camera gives rows with ``PIXELS`` and no ``OBSERVATION``. Nothing is dropped without a
warning.

Modules, one idea each: ``_layout`` (format constants, ``meta/info.json`` and its path
templates), ``_episodes`` (the episode and task tables), ``_files`` (every file of a load
opened by descriptor inside the dataset folder, pinned; metadata read whole bounded in
size and nesting), ``_frames`` (the frames read whole and checked against the episode
table), ``_locate``
(:func:`resolve_lerobot_root`: lerobot's folder and the hub caches, offline), ``_hub`` (a folder, a local cache or the Hub: :func:`download_lerobot`
into ``$HF_LEROBOT_HOME/hub`` as lerobot 0.6 does, one downloader at a time per
repository), ``_hub_http`` (the bounded HTTP client it asks the Hub through),
``_hub_limits`` (:class:`HubLimits`: timeouts, deadlines, size bounds, redirect hosts,
the file list's bounds, the wait for another download), ``_plan`` (feature -> buffer key, and why others are skipped),
``_read`` (:func:`load_lerobot`), ``_stream`` (``load_lerobot(..., into=buffer)``: a few
episodes at a time, everything checked before the buffer is extended), ``_video`` (where each episode's camera frames lie in
which mp4, and decoding them), ``_checks`` (what frames must satisfy: timestamps
against ``fps``, ``frame_index``, ``task_index``, the checksums :func:`save_lerobot`
records, and the edits LeRobot makes in place despite them), ``_write`` (:func:`save_lerobot`: rows -> features, written atomically by
``imitrl.fs.publish``), ``_write_frames`` (the data files and per-episode
statistics, a slice of whole episodes at a time), ``_episode_table`` (the episode table,
appended a slice at a time), ``_v3_files`` (the other files of a v3.0 directory),
``_stats`` (LeRobot's feature and image statistics, vectorised over episodes),
``_stats_totals`` (``meta/stats.json`` from running totals, with the digits of LeRobot's
aggregation over every episode at once), ``_metaworld`` (Meta-World recordings with
exactly ``lerobot/metaworld_mt50``'s features: :func:`save_metaworld_lerobot`).
"""

from imitrl.datasets.lerobot._dagger import save_dagger_lerobot
from imitrl.datasets.lerobot._hub import download_lerobot
from imitrl.datasets.lerobot._hub_limits import HubLimits

# the format's constants stay importable from here, as before the split into modules
from imitrl.datasets.lerobot._layout import (  # noqa: F401
    BOOKKEEPING,
    CODEBASE_VERSION,
    DATA_PATH,
    DEFAULT_CHUNK_SIZE,
    DEFAULT_DATA_FILE_SIZE_IN_MB,
    DEFAULT_KEY_MAP,
    DEFAULT_VIDEO_FILE_SIZE_IN_MB,
    EPISODES_PATH,
    IMAGE_NAMES,
    IMITRL_COLUMNS,
    INTERVENTION,
    QUANTILES,
    READ_VERSIONS,
    SIDECAR,
    SIDECAR_FORMAT,
)
from imitrl.datasets.lerobot._locate import resolve_lerobot_root
from imitrl.datasets.lerobot._metaworld import save_metaworld_lerobot
from imitrl.datasets.lerobot._read import load_lerobot
from imitrl.datasets.lerobot._write import save_lerobot

__all__ = [
    "DEFAULT_KEY_MAP",
    "IMITRL_COLUMNS",
    "HubLimits",
    "download_lerobot",
    "load_lerobot",
    "resolve_lerobot_root",
    "save_dagger_lerobot",
    "save_lerobot",
    "save_metaworld_lerobot",
]
