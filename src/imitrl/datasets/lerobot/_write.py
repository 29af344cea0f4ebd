"""Write demonstration rows as a LeRobot v3.0 dataset (:func:`save_lerobot`).

Rows are checked first (contiguous episodes whose ``STEP`` runs 0..length-1, tasks,
dtypes LeRobot can hold), turned into one arrow column per feature (or, with
``video=True``, one mp4 stream per camera: :mod:`~imitrl.datasets.lerobot._video_write`),
and written into a temporary directory that becomes ``path`` only once every file is
complete, atomically and with one writer per path
(:func:`~imitrl.datasets._publish.publishing`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import torch
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._arrow import encode_images, tensor_to_array
from imitrl.datasets._common import NUMPY_NAMES, key_name
from imitrl.datasets._publish import publishing
from imitrl.datasets.lerobot._layout import (
    BOOKKEEPING,
    DATASET_ENTRIES,
    DEFAULT_CHUNK_SIZE,
    DEFAULT_VIDEO_FILE_SIZE_IN_MB,
    IMAGE_NAMES,
    feature_name,
)
from imitrl.datasets.lerobot._v3_files import Episodes, Features, write_v3
from imitrl.datasets.lerobot._video_write import MIN_SIDE, import_av


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


def _image_feature(
    value: torch.Tensor, layout: Literal["hwc", "chw"], frame_index: np.ndarray
) -> tuple[pa.Array, dict, np.ndarray]:
    """A uint8 image key as LeRobot's image feature: PNG frames, its ``info.json`` entry,
    and the ``[N, C, H, W]`` frames its per-channel statistics read."""
    pixels = value.numpy() if layout == "hwc" else value.numpy().transpose(0, 2, 3, 1)
    column = encode_images(pixels, frame_index)
    chw = pixels.transpose(0, 3, 1, 2)  # (C, H, W), as LeRobot's stats read them
    entry = {"dtype": "image", "shape": list(tuple(value.shape[1:])), "names": IMAGE_NAMES[layout]}
    return column, entry, chw


def _video_feature(
    name: str, value: torch.Tensor, layout: Literal["hwc", "chw"]
) -> tuple[np.ndarray, dict, np.ndarray]:
    """A uint8 image key as LeRobot's video feature: the ``[N, H, W, 3]`` frames to encode
    (a view of ``value``), its ``info.json`` entry (``info`` is added once encoded), and the
    ``[N, C, H, W]`` frames its per-channel statistics read."""
    pixels = value.numpy() if layout == "hwc" else value.numpy().transpose(0, 2, 3, 1)
    if min(pixels.shape[1:3]) < MIN_SIDE:
        raise ValueError(
            f"{name!r}: frames of {pixels.shape[1]}x{pixels.shape[2]} (height x width) cannot "
            f"be encoded as video: SVT-AV1 needs at least {MIN_SIDE}x{MIN_SIDE}; save with "
            "video=False to store them as images"
        )
    entry = {"dtype": "video", "shape": list(pixels.shape[1:]), "names": IMAGE_NAMES["hwc"]}
    return pixels, entry, pixels.transpose(0, 3, 1, 2)


def _array_feature(
    name: str, value: torch.Tensor, names: Any, n_frames: int
) -> tuple[pa.Array, dict, np.ndarray]:
    """A key as a LeRobot array feature: its arrow column, its ``info.json`` entry, and
    the values its statistics read (``[N]`` for a per-frame scalar)."""
    column, shape = tensor_to_array(value)
    values = (
        value.numpy().reshape(n_frames, *shape)
        if shape != (1,)
        else value.numpy().reshape(n_frames)
    )
    entry = {
        "dtype": NUMPY_NAMES[value.dtype],
        "shape": list(shape),
        "names": _feature_names(name, names, shape),
    }
    return column, entry, values


def _features(
    rows: TensorDictBase,
    names: Mapping[str, Any],
    fps: int,
    episodes: Episodes,
    video: bool,
) -> Features:
    """Every leaf key as a feature (``STEP`` and ``"task_index"`` become bookkeeping; image
    keys become video features if ``video``), then LeRobot's bookkeeping columns."""
    n_frames = rows.shape[0]
    frame_index = rows.get(keys.STEP).numpy().astype(np.int64)
    out = Features({}, {}, {}, {}, {}, {})
    for key in rows.keys(include_nested=True, leaves_only=True):
        if key_name(key) in (keys.STEP, "task_index"):
            continue
        value = rows.get(key)
        if value.dtype not in NUMPY_NAMES:
            raise ValueError(f"{key_name(key)!r}: dtype {value.dtype} has no LeRobot equivalent")
        name = feature_name(key)
        if name in BOOKKEEPING:
            raise ValueError(f"{key_name(key)!r} would overwrite LeRobot's {name!r} column")
        out.sidecar[name] = {
            "key": list(key) if isinstance(key, tuple) else key,
            "shape": list(value.shape[1:]),
        }
        layout = _image_layout(name, value)
        if video:
            _check_camera(key, name, value, layout)
        if layout is not None and video:  # LeRobot's video feature: mp4 frames, image stats
            out.videos[name], entry, out.images[name] = _video_feature(name, value, layout)
            out.sidecar[name]["shape"] = entry["shape"]  # decoded frames are [H, W, 3]
        elif layout is not None:  # LeRobot's image feature: PNG frames, per-channel stats
            out.columns[name], entry, out.images[name] = _image_feature(value, layout, frame_index)
        else:
            column, entry, values = _array_feature(name, value, names.get(name), n_frames)
            out.columns[name] = column
            out.arrays[name] = values
        out.info[name] = entry
    if video and not out.videos:
        raise ValueError(
            "video=True but no key is a camera: a uint8 [N, H, W, 3] (or [N, 3, H, W]) key "
            f"{keys.PIXELS!r}, ({keys.PIXELS!r}, <camera>) or one whose feature name holds "
            f"'image'; keys: {[key_name(k) for k in rows.keys(True, True)]}"
        )
    book = {
        "timestamp": (frame_index / fps).astype(np.float32),
        "frame_index": frame_index,
        "episode_index": np.repeat(
            np.arange(len(episodes.lengths), dtype=np.int64), episodes.lengths
        ),
        "index": np.arange(n_frames, dtype=np.int64),
        "task_index": episodes.task_index.numpy(),
    }
    for name, values in book.items():
        out.columns[name] = pa.array(values)
        out.arrays[name] = values
        out.info[name] = {"dtype": str(values.dtype), "shape": [1], "names": None}
    if "task_index" in rows.keys():
        out.sidecar["task_index"] = {
            "key": "task_index",
            "shape": list(rows.get("task_index").shape[1:]),
        }
    return out


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
    """The ``[N]`` rows on the CPU, once they and the writer's settings are valid."""
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
    return rows.cpu()


def _episode_blocks(rows: TensorDictBase) -> tuple[list[int], list[int]]:
    """First row and length of each episode: contiguous blocks whose ``STEP`` runs
    0..length-1."""
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
    return starts, [e - s for s, e in zip(starts, ends)]


def _task_column(
    rows: TensorDictBase, tasks: str | Sequence[str]
) -> tuple[list[str], torch.Tensor]:
    """The task strings and each frame's ``[N]`` index into them."""
    n_frames = rows.shape[0]
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
    return task_list, task_index


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
    starts, lengths = _episode_blocks(rows)
    task_list, task_index = _task_column(rows, tasks)
    episodes = Episodes(starts, lengths, task_index, task_list)
    features = _features(rows, dict(names or {}), fps, episodes, video)
    if features.videos:
        import_av()  # before anything is written: a missing PyAV says how to install it
    table = features.table()
    with publishing(path, overwrite=overwrite, replaceable=_replaceable) as tmp:
        write_v3(
            tmp,
            table,
            features,
            episodes,
            fps=int(fps),
            robot_type=robot_type,
            episodes_per_file=episodes_per_file or len(starts),
            chunks_size=chunks_size,
            video_files_size_in_mb=video_files_size_in_mb,
        )
    return Path(path)
