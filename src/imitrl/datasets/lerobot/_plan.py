"""Which LeRobot feature is loaded into which buffer key, and why each other one is not.

The plan comes from ``meta/imitrl.json`` when :func:`save_lerobot` wrote the dataset
(exact keys and per-frame shapes), else from :data:`DEFAULT_KEY_MAP` and
:data:`IMITRL_COLUMNS`; ``key_map`` overrides either. Every feature left out gets a
reason, for the one warning :func:`load_lerobot` gives.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from imitrl import keys
from imitrl.datasets._common import NestedKey, as_key, key_name
from imitrl.datasets.lerobot._layout import (
    DEFAULT_KEY_MAP,
    IMITRL_COLUMNS,
    LEGACY_COLUMNS,
    SIDECAR,
    SIDECAR_FORMAT,
    camera_key,
    feature_name,
)

_LEFT_OUT = "left out by key_map"
"""why a feature ``key_map`` maps to None is skipped (listed, not warned about)"""


def _under(key: NestedKey, root_key: str) -> bool:
    return key == root_key or (isinstance(key, tuple) and key[0] == root_key)


def _under_observation(key: NestedKey) -> bool:
    return _under(key, keys.OBSERVATION)


_OWN_KEYS = frozenset(getattr(keys, name) for name in keys.__all__)
"""imitrl's row keys (:mod:`imitrl.keys`): no feature is loaded under one by its name"""


def plan_features(
    root: Path,
    info: dict,
    key_map: Mapping[str, NestedKey | None] | None,
    images: Literal["skip", "load"],
    videos: Literal["decode", "skip"],
    sidecar: object | None,
) -> tuple[dict[str, NestedKey], dict[str, tuple[int, ...]]]:
    """feature -> buffer key, and the exact per-frame shapes recorded by :func:`save_lerobot`
    (``sidecar``: ``meta/imitrl.json`` as read, None where the dataset has none).

    Video features map to :func:`~imitrl.datasets.lerobot._layout.camera_key` (under
    ``PIXELS``) unless ``key_map`` says otherwise; with ``videos="skip"`` none is planned.
    Without ``meta/imitrl.json`` and with no feature mapped to ``OBSERVATION`` (no
    ``observation.state``, say), every ``observation.<sub>`` feature that is not a camera
    maps to the nested key ``("observation", *sub.split("."))``: a Dict observation.
    """
    features = info["features"]
    if sidecar is not None:
        mapping, shapes = _sidecar_mapping(root / SIDECAR, sidecar, features, images)
    else:
        mapping = {k: v for k, v in DEFAULT_KEY_MAP.items() if k in features}
        ours = {**IMITRL_COLUMNS, **LEGACY_COLUMNS}
        mapping.update({k: v for k, v in ours.items() if k in features})
        shapes = {}
    for name, ft in features.items():
        if ft["dtype"] == "video" and name not in mapping:
            mapping[name] = camera_key(name)
    for name, key in (key_map or {}).items():
        if name not in features:
            raise ValueError(
                f"{root / 'meta' / 'info.json'}: key_map names feature {name!r}, which the "
                f"dataset does not declare (features: {sorted(features)})"
            )
        mapping[name] = key
    if sidecar is None and not any(
        v is not None and _under_observation(v) for v in mapping.values()
    ):
        mapping.update(_observation_group(features, mapping, images))
    plan = {
        k: v
        for k, v in mapping.items()
        if v is not None and (videos == "decode" or features[k]["dtype"] != "video")
    }
    _check_targets(root, plan, features)
    return plan, shapes


def _sidecar_mapping(
    sidecar: Path, meta: object, features: dict[str, dict], images: Literal["skip", "load"]
) -> tuple[dict[str, NestedKey | None], dict[str, tuple[int, ...]]]:
    """feature -> key and exact per-frame shape, as ``meta/imitrl.json`` (at ``sidecar``,
    ``meta`` as read) records them (image features only with ``images="load"``)."""
    if not isinstance(meta, dict) or meta.get("format") != SIDECAR_FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else meta
        raise ValueError(f"{sidecar}: unknown format {got!r}")
    if not isinstance(meta.get("columns"), dict):
        raise ValueError(f"{sidecar}: 'columns' must map features to keys and shapes")
    mapping: dict[str, NestedKey | None] = {}
    shapes: dict[str, tuple[int, ...]] = {}
    for name, entry in meta["columns"].items():
        if name not in features:
            raise ValueError(f"{sidecar}: column {name!r} is not a feature of meta/info.json")
        key, shape = _sidecar_entry(sidecar, name, entry, features[name])
        shapes[name] = shape
        if features[name]["dtype"] != "image" or images == "load":
            mapping[name] = key
    return mapping, shapes


def _sidecar_entry(
    sidecar: Path, name: str, entry: object, feature: dict
) -> tuple[NestedKey, tuple[int, ...]]:
    """One ``meta/imitrl.json`` column: its key (which :func:`save_lerobot` would have written
    as this very feature) and its exact per-frame shape (as many entries as ``info.json``'s)."""
    key = entry.get("key") if isinstance(entry, dict) else None
    shape = entry.get("shape") if isinstance(entry, dict) else None
    if (
        not (
            isinstance(key, str)
            or (isinstance(key, list) and key and all(isinstance(k, str) and k for k in key))
        )
        or as_key(key) == ""
        or (feature_name(as_key(key)) != name and LEGACY_COLUMNS.get(name) != as_key(key))
    ):
        raise ValueError(f"{sidecar}: column {name!r} records key {key!r}, not this feature's")
    pictures = feature["dtype"] in ("image", "video")
    if not isinstance(shape, list) or not all(
        isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape
    ):
        raise ValueError(
            f"{sidecar}: column {name!r} needs a shape (a list of sizes), got {shape!r}"
        )
    declared = feature["shape"]
    if math.prod(shape) != math.prod(declared) or (pictures and list(shape) != list(declared)):
        raise ValueError(
            f"{sidecar}: column {name!r} has shape {shape}, meta/info.json declares {declared}"
        )
    return as_key(key), tuple(shape)


def _observation_group(
    features: dict[str, dict],
    mapping: Mapping[str, NestedKey | None],
    images: Literal["skip", "load"],
) -> dict[str, NestedKey]:
    """Every loadable ``observation.<sub>`` feature not mapped yet ->
    ``("observation", *sub.split("."))``: a Dict observation."""
    prefix = keys.OBSERVATION + "."
    group: dict[str, NestedKey] = {}
    for name, ft in features.items():
        loadable = ft["dtype"] not in ("video", "string", "image") or (
            ft["dtype"] == "image" and images == "load"
        )
        if name.startswith(prefix) and name not in mapping and loadable:
            group[name] = (keys.OBSERVATION, *name.removeprefix(prefix).split("."))
    return group


def _check_targets(root: Path, plan: dict[str, NestedKey], features: dict[str, dict]) -> None:
    """Each key is loaded from one feature, is a tensor or a group (not both), and
    something is loaded under ``OBSERVATION`` or ``PIXELS`` (a camera-only dataset)."""
    targets = [key_name(v) for v in plan.values()]
    dup = sorted({t for t in targets if targets.count(t) > 1})
    if dup:
        named = sorted(k for k, v in plan.items() if key_name(v) in dup)
        raise ValueError(
            f"{root / 'meta' / 'info.json'}: features {named} all map to the buffer key(s) "
            f"{dup} (the dataset holds both of imitrl's names for one column?): drop one "
            "feature from the dataset, or choose one with key_map (load_lerobot)"
        )
    paths = {(v,) if isinstance(v, str) else tuple(v): k for k, v in plan.items()}
    for path, name in paths.items():
        for i in range(1, len(path)):
            if path[:i] in paths:
                raise ValueError(
                    f"{root / 'meta' / 'info.json'}: feature {paths[path[:i]]!r} maps to "
                    f"{key_name(path[:i])!r} and feature {name!r} inside it to "
                    f"{key_name(path)!r}; a key cannot be both a tensor and a group (fix key_map)"
                )
    if not any(_under_observation(v) or _under(v, keys.PIXELS) for v in plan.values()):
        numeric = [k for k, f in features.items() if f["dtype"] not in ("image", "video", "string")]
        raise ValueError(
            f"{root / 'meta' / 'info.json'}: no feature maps to {keys.OBSERVATION!r} (nor a "
            f"camera to {keys.PIXELS!r}); pass key_map={{'<feature>': {keys.OBSERVATION!r}}} "
            f"(features: {numeric})"
        )


def settle_features(
    root: Path,
    features: dict[str, dict],
    plan: dict[str, NestedKey],
    exact_shapes: dict[str, tuple[int, ...]],
    tasks: list[str],
    key_map: Mapping[str, NestedKey | None] | None,
    images: Literal["skip", "load"],
    videos: Literal["decode", "skip"],
) -> tuple[dict[str, NestedKey], dict[str, str], set[str]]:
    """The final plan (``task_index`` when there are several tasks, image features under
    their own names), every other feature -> why it is skipped, and the skipped features
    not warned about (bookkeeping, a single task, the caller's own ``key_map`` choices).

    ``task_index`` is loaded only for a dataset with several tasks that imitrl did not
    write (imitrl records it in ``meta/imitrl.json`` when the rows had it)."""
    plan = dict(plan)
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
        reason = _skip_reason(name, ft, tasks, quiet, key_map, images, videos)
        if reason is None:  # loaded under its own name, which must not be one of imitrl's
            if name in _OWN_KEYS:
                raise ValueError(
                    f"{root / 'meta' / 'info.json'}: feature {name!r} would be loaded under "
                    f"its own name, which is one of imitrl's keys: load it under another, "
                    f"key_map={{{name!r}: ('pixels', {name!r})}}, or skip it, "
                    f"key_map={{{name!r}: None}}"
                )
            plan[name] = name
            continue
        skipped[name] = reason
        if reason == _LEFT_OUT:
            quiet.add(name)  # the caller's choice: listed, not warned about
    _check_targets(root, plan, features)  # the features added here against the rest
    for name, key in plan.items():
        if features[name]["dtype"] == "string":
            raise ValueError(
                f"{root / 'meta' / 'info.json'}: feature {name!r} has dtype "
                f"{features[name]['dtype']!r}, which cannot be loaded into {key_name(key)!r}"
            )
    return plan, skipped, quiet


def _skip_reason(
    name: str,
    ft: dict,
    tasks: list[str],
    quiet: set[str],
    key_map: Mapping[str, NestedKey | None] | None,
    images: Literal["skip", "load"],
    videos: Literal["decode", "skip"],
) -> str | None:
    """Why an unplanned feature is not loaded; None for an image feature to load
    (``images="load"``)."""
    if name == "task_index" and name in quiet:
        return f"a single task ({tasks[0]!r})" if len(tasks) == 1 else "not recorded by imitrl"
    if key_map is not None and name in key_map:  # mapped to None: the caller leaves it out
        return _LEFT_OUT
    if ft["dtype"] == "video" and videos == "skip" and name not in (key_map or {}):
        return "video feature (mp4 under videos/) not decoded (videos='skip'; pass videos='decode')"
    if ft["dtype"] == "string":
        return "string feature: text cannot go into a tensor"
    if ft["dtype"] == "image" and images == "skip":
        return "image feature not loaded (images='skip'; pass images='load')"
    if ft["dtype"] == "image":
        return None
    if name in ("index", "timestamp"):
        return "bookkeeping (derivable from episode order and frame_index / fps)"
    return "no buffer key for it (add it to key_map)"
