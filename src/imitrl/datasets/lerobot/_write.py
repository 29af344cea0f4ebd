"""Write demonstration rows as a LeRobot v3.0 dataset (:func:`save_lerobot`).

Rows are checked first (contiguous episodes whose ``STEP`` runs 0..length-1, tasks,
dtypes LeRobot can hold, read a slice at a time), then read again a slice of whole
episodes at a time and turned into arrow columns, one per feature, and per-episode
statistics (:mod:`~imitrl.datasets.lerobot._write_frames`; or, with ``video=True``, one
mp4 stream per camera: :mod:`~imitrl.datasets.lerobot._video_write`), so that memory does
not grow with the number of rows (a disk buffer's rows are read from its files), and
written into a temporary directory that becomes ``path`` only once every file is
complete, atomically and with one writer per path
(:func:`~imitrl.fs.publish.publishing`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.data.disk import release_pages
from imitrl.datasets._arrow import array_shape
from imitrl.datasets._common import NUMPY_NAMES, key_name
from imitrl.datasets.lerobot._layout import (
    BOOKKEEPING,
    DATASET_ENTRIES,
    DEFAULT_CHUNK_SIZE,
    DEFAULT_VIDEO_FILE_SIZE_IN_MB,
    IMAGE_NAMES,
    feature_name,
)
from imitrl.datasets.lerobot._v3_files import write_v3
from imitrl.datasets.lerobot._video_write import MIN_SIDE, import_av
from imitrl.datasets.lerobot._write_frames import pixels_of
from imitrl.datasets.lerobot._write_plan import (
    Column,
    Episodes,
    Plan,
    check_finite_rows,
    check_timestamps,
)
from imitrl.fs.publish import publishing


# -------------------------------------------------------------- features
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


def _array_entry(name: str, value: torch.Tensor, names: Any) -> dict:
    """A key's ``info.json`` entry as a LeRobot array feature (``[N]`` and ``[N, 1]``:
    shape ``(1,)``, LeRobot's layout for a per-frame scalar)."""
    shape = array_shape(tuple(value.shape[1:]))
    return {
        "dtype": NUMPY_NAMES[value.dtype],
        "shape": list(shape),
        "names": _feature_names(name, names, shape),
    }


def _video_entry(name: str, value: torch.Tensor, layout: Literal["hwc", "chw"]) -> dict:
    """A uint8 image key's ``info.json`` entry as a LeRobot video feature (``info`` is added
    once encoded); frames too small for SVT-AV1 are refused."""
    height, width = value.shape[1:3] if layout == "hwc" else value.shape[2:4]
    if min(height, width) < MIN_SIDE:
        raise ValueError(
            f"{name!r}: frames of {height}x{width} (height x width) cannot "
            f"be encoded as video: SVT-AV1 needs at least {MIN_SIDE}x{MIN_SIDE}; save with "
            "video=False to store them as images"
        )
    return {"dtype": "video", "shape": [height, width, 3], "names": IMAGE_NAMES["hwc"]}


def _plan(
    rows: TensorDictBase,
    names: Mapping[str, Any],
    video: bool,
    features: Sequence[str] | None = None,
) -> Plan:
    """Every leaf key as a feature (``STEP`` and ``"task_index"`` become bookkeeping; image
    keys become video features if ``video``; only the ``features`` named, if given), then
    LeRobot's bookkeeping columns; from the keys' dtypes and shapes alone (no row is read)."""
    _check_features(rows, features)
    columns: list[Column] = []
    info: dict[str, dict] = {}
    sidecar: dict[str, dict] = {}
    videos: dict[str, np.ndarray] = {}
    for key in rows.keys(include_nested=True, leaves_only=True):
        if key_name(key) in (keys.STEP, "task_index"):
            continue
        if features is not None and feature_name(key) not in features:
            continue
        value = rows.get(key)
        if value.dtype not in NUMPY_NAMES:
            raise ValueError(f"{key_name(key)!r}: dtype {value.dtype} has no LeRobot equivalent")
        name = feature_name(key)
        if name in BOOKKEEPING:
            raise ValueError(f"{key_name(key)!r} would overwrite LeRobot's {name!r} column")
        sidecar[name] = {
            "key": list(key) if isinstance(key, tuple) else key,
            "shape": list(value.shape[1:]),
        }
        layout = _image_layout(name, value)
        if video:
            _check_camera(key, name, value, layout)
        if layout is not None and video:  # LeRobot's video feature: mp4 frames, image stats
            info[name] = _video_entry(name, value, layout)
            videos[name] = pixels_of(value, layout)
            sidecar[name]["shape"] = info[name]["shape"]  # decoded frames are [H, W, 3]
            columns.append(Column(key, name, "video", layout))
        elif layout is not None:  # LeRobot's image feature: PNG frames, per-channel stats
            shape = list(tuple(value.shape[1:]))
            info[name] = {"dtype": "image", "shape": shape, "names": IMAGE_NAMES[layout]}
            columns.append(Column(key, name, "image", layout))
        else:
            info[name] = _array_entry(name, value, names.get(name))
            columns.append(Column(key, name, "array", None))
    if video and not videos:
        raise ValueError(
            "video=True but no key is a camera: a uint8 [N, H, W, 3] (or [N, 3, H, W]) key "
            f"{keys.PIXELS!r}, ({keys.PIXELS!r}, <camera>) or one whose feature name holds "
            f"'image'; keys: {[key_name(k) for k in rows.keys(True, True)]}"
        )
    for name in BOOKKEEPING:
        dtype = "float32" if name == "timestamp" else "int64"
        info[name] = {"dtype": dtype, "shape": [1], "names": None}
    if "task_index" in rows.keys():
        sidecar["task_index"] = {
            "key": "task_index",
            "shape": list(rows.get("task_index").shape[1:]),
        }
    return Plan(columns, info, sidecar, videos)


def _check_features(rows: TensorDictBase, features: Sequence[str] | None) -> None:
    """Every name of ``features`` is a feature the rows give (ValueError naming them)."""
    if features is None:
        return
    if isinstance(features, str):
        raise ValueError(f"features must be a list of feature names, got the string {features!r}")
    given = {feature_name(k) for k in rows.keys(include_nested=True, leaves_only=True)}
    missing = [f for f in features if f not in given and f not in BOOKKEEPING]
    if missing:
        raise ValueError(
            f"features {missing} are not in the rows, which give {sorted(given)} (LeRobot's "
            f"bookkeeping {list(BOOKKEEPING)} is always written)"
        )


def _check_camera(
    key: Any, name: str, value: torch.Tensor, layout: Literal["hwc", "chw"] | None
) -> None:
    """With ``video=True``, a key under ``PIXELS`` must be a uint8 ``[N, H, W, 3]`` (or
    ``[N, 3, H, W]``) camera: it would otherwise be written as a plain array, silently."""
    under_pixels = key == keys.PIXELS or (isinstance(key, tuple) and key[0] == keys.PIXELS)
    if under_pixels and layout is None:
        raise ValueError(
            f"{key_name(key)!r} (feature {name!r}): video=True writes it as a LeRobot video, "
            f"which needs uint8 [N, H, W, 3] or [N, 3, H, W] frames; got {value.dtype} "
            f"{list(value.shape)}"
        )


# ------------------------------------------------------------------ rows
def _rows_to_write(
    data: DemonstrationBuffer | TensorDictBase,
    fps: int,
    episodes_per_file: int | None,
    chunks_size: int,
) -> TensorDictBase:
    """The ``[N]`` rows (a view: read a slice at a time), once they and the writer's settings
    are valid."""
    rows = data.data if isinstance(data, DemonstrationBuffer) else data
    if not isinstance(rows, TensorDictBase) or rows.batch_dims != 1 or rows.shape[0] == 0:
        raise ValueError("save_lerobot needs a non-empty buffer or a TensorDict of rows [N]")
    for k in (keys.EPISODE, keys.STEP):
        if k not in rows.keys():
            raise ValueError(f"rows need {k!r} to be written as a LeRobot dataset")
    if keys.OBSERVATION not in rows.keys() and keys.PIXELS not in rows.keys():
        raise ValueError(
            f"rows need {keys.OBSERVATION!r} or a camera {keys.PIXELS!r} (what load_lerobot "
            "gives for a camera-only dataset) to be written as a LeRobot dataset; keys: "
            f"{[key_name(k) for k in rows.keys(True, True)]}"
        )
    if keys.EXPERT_ACTION not in rows.keys() and keys.ACTION not in rows.keys():
        raise ValueError(f"rows need {keys.EXPERT_ACTION!r} (or {keys.ACTION!r})")
    if int(fps) != fps or fps <= 0:
        raise ValueError(f"fps must be a positive integer, got {fps!r}")
    if episodes_per_file is not None and episodes_per_file < 1:
        raise ValueError(f"episodes_per_file must be >= 1, got {episodes_per_file}")
    if chunks_size < 1:
        raise ValueError(f"chunks_size must be >= 1, got {chunks_size}")
    return rows


SCAN_ROWS = 1 << 18
"""rows of ``EPISODE``, ``STEP`` and ``task_index`` read at once by :func:`_episodes`"""


def _episodes(rows: TensorDictBase, tasks: str | Sequence[str]) -> Episodes:
    """Each episode's first row, length and tasks, read :data:`SCAN_ROWS` rows at a time:
    episodes are contiguous blocks whose ``STEP`` runs 0..length-1, and ``"task_index"``
    (required with several tasks) indexes ``tasks``. Memory: a few integers per episode
    (a memory-mapped source's pages are let go after each read)."""
    n = rows.shape[0]
    task_list = [tasks] if isinstance(tasks, str) else list(tasks)
    if not task_list or len(set(task_list)) != len(task_list):
        raise ValueError(f"tasks must be distinct strings, got {task_list!r}")
    has_tasks = "task_index" in rows.keys()
    if not has_tasks and len(task_list) != 1:
        raise ValueError("several tasks given but the rows have no 'task_index' key")
    scanned = rows.select(keys.EPISODE, keys.STEP, *(["task_index"] if has_tasks else []))
    starts: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    pairs: list[np.ndarray] = []  # episode number * len(task_list) + task index
    count, last_id, run_start = 0, None, 0
    wrong_step: str | None = None
    for begin in range(0, n, SCAN_ROWS):
        end = min(n, begin + SCAN_ROWS)
        part = scanned[begin:end]
        episode = part.get(keys.EPISODE).cpu().numpy().reshape(-1)
        step = part.get(keys.STEP).cpu().numpy().reshape(-1)
        change = np.ones(end - begin, dtype=bool)
        change[1:] = episode[1:] != episode[:-1]
        change[0] = last_id is None or int(episode[0]) != last_id
        where = np.arange(begin, end)
        first = np.maximum.accumulate(np.where(change, where, run_start))  # each row's run start
        bad = np.flatnonzero(step != where - first)
        if len(bad) and wrong_step is None:  # raised after the contiguity check
            i = int(bad[0])
            wrong_step = (
                f"episode {int(episode[i])}: {keys.STEP!r} must run 0..length-1 (LeRobot's "
                f"frame_index), got {int(step[i])} at its row {int(where[i] - first[i])}"
            )
        number = count + np.cumsum(change) - 1  # each row's episode
        count += int(change.sum())
        starts.append(where[change])
        ids.append(episode[change])
        if has_tasks:
            task = part.get("task_index").cpu().reshape(-1).to(torch.int64).numpy()
            if int(task.min()) < 0 or int(task.max()) >= len(task_list):
                raise ValueError(
                    f"'task_index' holds indices outside the {len(task_list)} tasks given"
                )
            pairs.append(np.unique(number * len(task_list) + task))
        last_id, run_start = int(episode[-1]), int(first[-1])
        release_pages(part)
    all_starts = np.concatenate(starts).astype(np.int64)
    all_ids = np.concatenate(ids)
    if len(np.unique(all_ids)) != len(all_ids):
        raise ValueError(
            "each episode must be one contiguous block of rows (an id reappears later)"
        )
    if wrong_step is not None:
        raise ValueError(wrong_step)
    both = np.unique(np.concatenate(pairs)) if has_tasks else np.arange(count) * len(task_list)
    task_pairs = np.stack([both // len(task_list), both % len(task_list)], axis=1)
    lengths = np.diff(np.append(all_starts, n)).astype(np.int64)
    return Episodes(all_starts, lengths, task_pairs.astype(np.int64), task_list)


def _replaceable(path: Path) -> None:
    """``overwrite=True`` replaces only a LeRobot dataset directory: one whose
    ``meta/info.json`` names a ``codebase_version`` (LeRobot and :func:`save_lerobot` write
    one) and that holds nothing beside the dataset's own entries (:data:`DATASET_ENTRIES`:
    ``meta``, ``data``, ``videos``, ``images``, a hub download's ``README.md``,
    ``.gitattributes`` and ``.cache``). Anything else is someone's folder: ValueError."""
    try:
        info = json.loads((path / "meta" / "info.json").read_text())
    except (OSError, ValueError):
        info = None
    if not isinstance(info, dict) or not isinstance(info.get("codebase_version"), str):
        raise ValueError(
            f"{path} is not a LeRobot dataset (no meta/info.json naming a codebase_version); "
            "overwrite=True replaces only a dataset: refusing to delete it"
        )
    other = sorted(p.name for p in path.iterdir() if p.name not in DATASET_ENTRIES)
    if other:
        raise ValueError(
            f"{path} holds {other} beside the dataset; overwrite=True replaces only a directory "
            f"holding nothing but a LeRobot dataset ({sorted(DATASET_ENTRIES)}): refusing"
        )


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
    video: bool = False,
    video_files_size_in_mb: float = DEFAULT_VIDEO_FILE_SIZE_IN_MB,
    features: Sequence[str] | None = None,
) -> Path:
    """Write demonstrations as a LeRobot v3.0 dataset that LeRobot's own reader opens.

    Every leaf key becomes a feature: ``OBSERVATION -> observation.state``,
    ``EXPERT_ACTION -> action`` (the label a LeRobot policy trains on),
    ``("next", k) -> next.k``, ``ACTION -> imitrl.executed_action``,
    ``EXPERT_EXECUTED -> intervention`` (LeRobot's DAgger column, bool ``(1,)``),
    ``ROUND -> imitrl.round``, ``BETA -> imitrl.beta``, ``POLICY_VERSION ->
    imitrl.policy_version``, ``EPISODE -> imitrl.episode`` (LeRobot's ``episode_index``
    must run 0..E-1),
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
            runs 0..length-1 (as :func:`~imitrl.runtime.rollout_episodes` produces); with
            ``OBSERVATION``, or only a camera ``PIXELS`` (what :func:`load_lerobot` gives
            for a camera-only dataset).
        path: the dataset directory (must not exist unless ``overwrite``; never the working
            directory or one holding it).
        fps: frames per second (``timestamp = frame_index / fps``).
        tasks: the task of every frame, or the task strings a ``"task_index"`` key indexes.
        robot_type: written to ``info.json``.
        episodes_per_file: episodes per data file (None: all in one file); files roll
            over into ``chunk-001`` ... after ``chunks_size`` files.
        chunks_size: files per chunk directory (LeRobot's ``chunks_size``).
        names: feature -> LeRobot ``names`` for ``info.json`` (None, a list with one string
            per entry of a vector, or a mapping to such lists); to keep a source dataset's,
            pass ``{f: ft["names"] for f, ft in loaded.metadata["features"].items()}``.
            Entries for features not written (bookkeeping, skipped features) are
            ignored; image and video features always get their layout's names. Default: None
            for all.
        overwrite: replace an existing LeRobot dataset that holds nothing else
            (:func:`_replaceable`); the old one stays whole until the new one is complete.
        video: write every image key (a uint8 ``[N, H, W, 3]`` or ``[N, 3, H, W]`` key
            ``PIXELS`` -> ``observation.image``, ``(PIXELS, cam)`` ->
            ``observation.images.<cam>``, or one whose feature name holds ``"image"``) as a
            LeRobot video feature instead of PNG frames: AV1 mp4 files encoded as LeRobot
            encodes them, ``videos/<feature>/chunk-XXX/file-YYY.mp4``, episodes back to back
            with their ``from_timestamp``/``to_timestamp`` in the episode table
            (:mod:`~imitrl.datasets.lerobot._video_write`). Needs PyAV
            (``pip install 'imitrl[datasets]'``). AV1 is lossy: frames load back close to,
            not equal to, the source (32-37 dB PSNR on small smooth test images).
        video_files_size_in_mb: a camera's episodes go into one mp4 file until the next
            would bring it to this size, then into the next file (LeRobot's
            ``video_files_size_in_mb``).
        features: write only these features (names as above) beside LeRobot's
            bookkeeping columns, e.g. a published dataset's exact feature set
            (:data:`imitrl.envs.metaworld.LEROBOT_FEATURES`); the rows' ``EPISODE`` and
            ``STEP`` still delimit the episodes. Without imitrl's own columns
            (``imitrl.*``) :func:`load_lerobot` reads the dataset as it reads LeRobot's
            (episodes by ``episode_index``, one round). None: every key.

    Returns:
        the dataset directory.

    Raises:
        ValueError: rows LeRobot cannot hold; ``video=True`` without a camera key, or with
            a ``PIXELS`` key that is no uint8 image; ``path`` exists (without
            ``overwrite``), is no replaceable dataset, is or holds the working directory,
            or another process is writing it. Under any error or kill ``path`` keeps what
            it held.
        ImportError: ``video=True`` and PyAV is not installed (the message says how).
    """
    rows = _rows_to_write(data, fps, episodes_per_file, chunks_size)
    size = video_files_size_in_mb
    if isinstance(size, bool) or not isinstance(size, int | float) or not size > 0:
        raise ValueError(f"video_files_size_in_mb must be > 0, got {video_files_size_in_mb!r}")
    episodes = _episodes(rows, tasks)
    check_timestamps(int(episodes.lengths.max()), int(fps))
    if not isinstance(data, DemonstrationBuffer):  # a buffer's rows were checked on extend
        check_finite_rows(rows)
    plan = _plan(rows, dict(names or {}), video, features)
    if plan.videos:
        import_av()  # before anything is written: a missing PyAV says how to install it
    with publishing(path, overwrite=overwrite, replaceable=_replaceable) as tmp:
        write_v3(
            tmp,
            rows,
            plan,
            episodes,
            fps=int(fps),
            robot_type=robot_type,
            episodes_per_file=episodes_per_file or len(episodes.starts),
            chunks_size=chunks_size,
            video_files_size_in_mb=video_files_size_in_mb,
        )
    return Path(path).expanduser()
