"""What a LeRobot dataset's ``meta/info.json`` says.

The format's constants (versions, path templates, the column <-> key maps), reading
``meta/info.json`` (validated where it is read, its feature names bounded:
:data:`MAX_FEATURE_NAME_BYTES`) and filling its path templates (their format widths
bounded: :data:`MAX_TEMPLATE_WIDTH`). The episode and task tables:
:mod:`~imitrl.datasets.lerobot._episodes`; finding a dataset on disk:
:mod:`~imitrl.datasets.lerobot._locate`.
"""

from __future__ import annotations

import math
import re
import string
from pathlib import Path

from imitrl import keys
from imitrl.datasets._common import NestedKey, key_name
from imitrl.datasets.lerobot._files import read_json
from imitrl.fs.contained import check_relative
from imitrl.fs.reading import OpenedFolder

DEFAULT_KEY_MAP: dict[str, NestedKey] = {
    "observation.state": keys.OBSERVATION,
    "action": keys.EXPERT_ACTION,
    "next.reward": (keys.NEXT, keys.REWARD),
    "next.done": (keys.NEXT, keys.DONE),
    "next.terminated": (keys.NEXT, keys.TERMINATED),
    "next.truncated": (keys.NEXT, keys.TRUNCATED),
    "observation.environment_state": keys.ENVIRONMENT_STATE,
    "intervention": keys.EXPERT_EXECUTED,
}
"""dataset feature -> buffer key, applied unless ``key_map`` overrides an entry (``task_index``
is loaded as ``"task_index"`` when the dataset has more than one task)"""

INTERVENTION = "intervention"
"""LeRobot's DAgger column (``lerobot/rollout/strategies/dagger.py``: bool, shape ``(1,)``,
True on the frames a human's correction was executed): ``EXPERT_EXECUTED``, both ways"""

IMITRL_COLUMNS: dict[str, NestedKey] = {
    "imitrl.executed_action": keys.ACTION,
    "imitrl.round": keys.ROUND,
    "imitrl.episode": keys.EPISODE,
    "imitrl.beta": keys.BETA,
    "imitrl.policy_version": keys.POLICY_VERSION,
}
"""the columns :func:`save_lerobot` adds so that DAgger rounds round-trip (with
:data:`INTERVENTION`)"""

LEGACY_COLUMNS: dict[str, NestedKey] = {"imitrl.expert_executed": keys.EXPERT_EXECUTED}
"""columns imitrl wrote before it wrote LeRobot's own :data:`INTERVENTION`: still read"""

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
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
IMAGE_NAMES = {"hwc": ["height", "width", "channels"], "chw": ["channels", "height", "width"]}
DATASET_ENTRIES = frozenset(
    {"meta", "data", "videos", "images", "README.md", ".gitattributes", ".cache"}
)
"""what the top level of a LeRobot dataset directory holds (a hub download adds the last three)"""
SIDECAR = "meta/imitrl.json"
SIDECAR_FORMAT = "imitrl.lerobot/1"
MAX_FEATURE_NAME_BYTES = 249
"""UTF-8 bytes a feature name may hold: a camera's name becomes the file name
``<feature>.uint8`` (``decode_dir``), which the file system keeps to 255 bytes; LeRobot's
own names hold a few dozen (``observation.images.wrist_left``)"""
MAX_TEMPLATE_WIDTH = 32
"""the largest width or precision a field of a path template may ask for (LeRobot's
templates ask for 3 and 6: ``{episode_index:06d}``)"""
MAX_TEMPLATE_CHARS = 4096
"""characters a path template may hold (the longest path Linux opens, ``PATH_MAX``)"""


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
        keys.EXPERT_EXECUTED: INTERVENTION,
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


# -------------------------------------------------------------------- info.json
def read_info(folder: OpenedFolder) -> tuple[dict, int]:
    """``meta/info.json``, validated, and its layout's major version (2 or 3)."""
    path = folder.root / "meta" / "info.json"
    info = read_json(folder, "meta/info.json")
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
    _check_template(path, "data_path", info["data_path"])
    if isinstance(info.get("video_path"), str):  # None without cameras; checked where used
        _check_template(path, "video_path", info["video_path"])
    major = READ_VERSIONS.get(str(info["codebase_version"]))
    if major is None:
        raise ValueError(
            f"{path}: codebase_version {_short(info['codebase_version'])} is not supported "
            f"(only {', '.join(READ_VERSIONS)} are)"
        )
    if not isinstance(info["features"], dict):
        raise ValueError(f"{path}: 'features' must map feature names to descriptions")
    for name, ft in info["features"].items():
        _check_feature_name(path, name)
        if not isinstance(ft, dict) or not isinstance(ft.get("dtype"), str):
            raise ValueError(
                f"{path}: feature {name!r} needs a dtype and a shape, got {_short(ft)}"
            )
        shape = ft.get("shape")
        if not isinstance(shape, list | tuple) or not all(
            isinstance(d, int) and d >= 0 for d in shape
        ):
            raise ValueError(
                f"{path}: feature {name!r} needs a shape (a list of sizes), got {_short(shape)}"
            )
    return info, major


def _short(value: object, keep: int = 60) -> str:
    """``repr(value)``, cut to ``keep`` characters (a hostile entry may be megabytes)."""
    text = repr(value)
    return text if len(text) <= keep else f"{text[:keep]}... ({len(text):,} characters)"


def _check_feature_name(path: Path, name: str) -> None:
    """A feature name is a dotted name: LeRobot joins it with ``/`` into the episode
    table's columns (``videos/<feature>/...``, ``stats/<feature>/...``), so ``/`` can be
    none of its characters; nor ``\\``, a NUL or a control character, and it is never
    ``.`` or ``..``: a camera's name becomes a file name (``decode_dir``), hence at most
    :data:`MAX_FEATURE_NAME_BYTES` bytes."""
    if len(name.encode(errors="replace")) > MAX_FEATURE_NAME_BYTES:
        raise ValueError(
            f"{path}: feature name {_short(name)} is longer than the "
            f"{MAX_FEATURE_NAME_BYTES} bytes a LeRobot feature name may hold (a dotted name "
            "such as 'observation.images.top')"
        )
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


_NUMBER = re.compile(r"[0-9]+")


def _check_template(path: Path, field: str, template: object) -> str:
    """A path template of at most :data:`MAX_TEMPLATE_CHARS` characters whose fields are
    plain names with a format spec asking for at most :data:`MAX_TEMPLATE_WIDTH`
    characters (``{episode_index:0999999999d}`` would build a gigabyte string), read with
    ``string.Formatter().parse`` before anything is formatted."""
    if not isinstance(template, str):
        raise ValueError(f"{path}: {field} must be a path template, got {_short(template)}")
    if len(template) > MAX_TEMPLATE_CHARS:
        raise ValueError(
            f"{path}: {field} holds {len(template):,} characters, more than the "
            f"{MAX_TEMPLATE_CHARS} of a path"
        )
    try:
        parsed = list(string.Formatter().parse(template))
    except ValueError as err:
        raise ValueError(f"{path}: {field} {template!r} is not a path template ({err})") from None
    for _, name, spec, _ in parsed:
        if name is None:
            continue
        numbers = [n.lstrip("0") or "0" for n in _NUMBER.findall(spec or "")]
        if "{" in (spec or "") or any(len(n) > 3 or int(n) > MAX_TEMPLATE_WIDTH for n in numbers):
            raise ValueError(
                f"{path}: {field} {_short(template)} asks for {{{name}:{(spec or '')[:20]}}}, "
                f"a format width past {MAX_TEMPLATE_WIDTH} characters (LeRobot's templates "
                "ask for 3 or 6: data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}"
                ".parquet); refused before formatting it"
            )
    return template


def fill_template(root: Path, info: dict, field: str, **fields: int | str) -> str:
    """``info.json``'s path template ``field`` (``data_path``, ``video_path``) filled in
    (:func:`_check_template` first), naming the template when it breaks; a path out of the
    dataset folder (absolute, ``..``) is refused here, a link out where it is opened
    (:meth:`~imitrl.fs.reading.OpenedFolder.open`)."""
    path = root / "meta" / "info.json"
    template = _check_template(path, field, info.get(field))
    try:
        filled = template.format(**fields)
    except (KeyError, IndexError, ValueError, AttributeError, TypeError) as err:
        raise ValueError(
            f"{path}: {field} {template!r} cannot be filled "
            f"with {sorted(fields)} ({type(err).__name__}: {err})"
        ) from err
    check_relative(root, filled, named_by=f"meta/info.json's {field} {template!r}")
    return filled


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
