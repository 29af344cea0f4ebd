"""What a LeRobot dataset's frames must satisfy before a row is returned.

LeRobot's own reader assumes these and mostly does not check them: ``fps`` is a
positive number and consecutive timestamps of an episode lie ``1 / fps`` apart within
``tolerance_s = 1e-4`` s (``LeRobotDataset(tolerance_s=1e-4)``, checked by
``check_timestamps_sync`` in ``lerobot/datasets/utils.py``); ``frame_index`` runs
0..length-1 in every episode; ``task_index`` indexes the task table. Datasets
:func:`save_lerobot` wrote also carry each file's size and SHA-256 in
``meta/imitrl.json``: a file changed since (a flipped byte, a truncation) is refused
by name, since a parquet file has no checksum of its own and a changed value would
otherwise load as data. LeRobot's own edits in place (it resumes recording into the
dataset, or recomputes its statistics, and leaves ``meta/imitrl.json`` behind) are told
apart from that: they rewrite only ``meta/info.json`` (its totals), ``meta/stats.json``
and ``meta/tasks.parquet`` and add new files (:func:`verify_files`).
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path
from typing import Any

import torch

from imitrl.datasets._common import open_in
from imitrl.datasets.lerobot._files import holds, list_files, read_json
from imitrl.datasets.lerobot._layout import IMITRL_COLUMNS, LEGACY_COLUMNS, SIDECAR
from imitrl.fs.contained import check_relative
from imitrl.fs.reading import OpenedFolder

TOLERANCE_S = 1e-4
"""LeRobot's timestamp tolerance (``LeRobotDataset``'s ``tolerance_s`` default)"""


def file_digest(path: Path) -> dict[str, Any]:
    """``{"size": bytes, "sha256": hex}`` of a file, as ``meta/imitrl.json`` records it."""
    with open(path, "rb") as f:
        return _digest(f)


def _digest(f: Any) -> dict[str, Any]:
    """:func:`file_digest` of an open file, read from its start."""
    digest = hashlib.sha256()
    size = 0
    for block in iter(lambda: f.read(1 << 20), b""):
        digest.update(block)
        size += len(block)
    return {"size": size, "sha256": digest.hexdigest()}


def _folder_digest(folder: OpenedFolder, name: str, named_by: str) -> dict[str, Any]:
    """:func:`file_digest` of the file ``name`` of the folder, opened inside it."""
    with os.fdopen(open_in(folder, name, named_by=named_by), "rb") as f:
        return _digest(f)


def sidecar_digest(sidecar: dict) -> str:
    """SHA-256 of ``meta/imitrl.json``'s own content (every entry but ``"digest"``), so that
    a changed key or shape in it is caught like a changed byte in the files it lists."""
    content = {k: v for k, v in sidecar.items() if k != "digest"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


LEROBOT_REWRITES = ("meta/info.json", "meta/stats.json", "meta/tasks.parquet")
"""the files LeRobot rewrites in place: all three when it resumes recording
(``LeRobotDataset.resume``: totals, statistics, a new task), ``meta/stats.json`` when it
recomputes statistics (``lerobot-edit-dataset --operation.type recompute_stats``)"""

LEROBOT_ADDS = ("data", "meta/episodes", "videos", "images")
"""where LeRobot puts the files of the episodes it adds: always new files (lerobot 0.4 and
0.6 move to the next ``file-*`` when they resume), never into a file already written"""

INFO_TOTALS = ("total_episodes", "total_frames", "total_tasks", "splits")
"""the entries of ``meta/info.json`` LeRobot changes in place (``save_episode``); every
other entry (``features``, ``fps``, the path templates, ...) it keeps"""


def verify_files(folder: OpenedFolder, sidecar: object) -> list[str]:
    """``meta/imitrl.json`` (``sidecar``, as read) is as written (its ``"digest"``) and every
    file it lists is there with its recorded size and SHA-256, but for LeRobot's own edits
    in place.

    LeRobot leaves ``meta/imitrl.json`` behind when it edits a dataset: it rewrites the
    files of :data:`LEROBOT_REWRITES` and adds files under :data:`LEROBOT_ADDS`. Such a
    dataset is still a LeRobot dataset: the rewritten files lose their checksums, and
    ``meta/info.json`` must keep every entry but :data:`INFO_TOTALS` as recorded (sidecars
    with an ``"info"`` record) and a rewritten ``meta/stats.json`` must be LeRobot's
    statistics; the rest is checked as for any LeRobot dataset. Any other change (a byte
    of a data file, an episode table, a video; the sidecar itself) is refused by name.
    Every file is read inside ``folder``, opened by descriptor.

    Returns:
        the files LeRobot rewrote or added since :func:`save_lerobot` wrote the dataset
        (``[]``: as written). A sidecar with neither ``"files"`` nor ``"digest"`` (imitrl
        before checksums) is not verified.
    """
    root = folder.root
    where = root / SIDECAR
    if not isinstance(sidecar, dict) or ("files" not in sidecar and "digest" not in sidecar):
        return []  # a sidecar that is not an object is refused where it is read
    if sidecar.get("digest") != sidecar_digest(sidecar):
        raise ValueError(
            f"{where}: changed since save_lerobot wrote it (its content does not match its "
            "digest); refusing to load altered data"
        )
    files = sidecar.get("files")
    if not isinstance(files, dict):
        raise ValueError(f"{where}: 'files' must map file names to sizes and checksums")
    rewritten = []
    for name, recorded in files.items():
        check_relative(root, name, named_by=str(where))
        path = root / name
        if not holds(folder, name):
            raise ValueError(f"{path}: file not found (listed in {where})")
        if _folder_digest(folder, name, str(where)) == recorded:
            continue
        if name not in LEROBOT_REWRITES:
            raise ValueError(
                f"{path}: changed since save_lerobot wrote it (its size or SHA-256 differs from "
                f"{where}; LeRobot adds episodes in new files and never rewrites this one); "
                "refusing to load altered data"
            )
        rewritten.append(name)
    added = [
        name
        for top in LEROBOT_ADDS
        for name in list_files(folder, top, suffix="", depth=None)
        if name not in files
    ]
    if "meta/info.json" in rewritten:
        _check_info_kept(folder, sidecar.get("info"))
    if "meta/stats.json" in rewritten:
        _check_stats(folder)
    return rewritten + added


def _check_info_kept(folder: OpenedFolder, recorded: object) -> None:
    """A rewritten ``meta/info.json`` keeps every entry :func:`save_lerobot` recorded but
    :data:`INFO_TOTALS`, as LeRobot keeps them."""
    if not isinstance(recorded, dict):
        return  # a sidecar from before the record: the columns are checked against it on load
    path = folder.root / "meta" / "info.json"
    info = read_json(folder, "meta/info.json")
    if not isinstance(info, dict):
        return  # refused by name where it is read
    for field, was in recorded.items():
        now = info.get(field)
        if field in INFO_TOTALS or now == was:
            continue
        what = repr(field)
        if field == "features" and isinstance(now, dict) and isinstance(was, dict):
            name = next((n for n in dict.fromkeys([*was, *now]) if now.get(n) != was.get(n)), None)
            what, now, was = f"feature {name!r}", now.get(name), was.get(name)
        raise ValueError(
            f"{path}: {what} is {now!r}, save_lerobot wrote {was!r} (recorded in "
            f"{folder.root / SIDECAR}); LeRobot changes only {list(INFO_TOTALS)} of an existing "
            "dataset, so this is not its edit: refusing altered data (delete meta/imitrl.json "
            "to read the folder as any LeRobot dataset)"
        )


def _check_stats(folder: OpenedFolder) -> None:
    """``meta/stats.json`` as LeRobot writes it (``write_stats``): feature -> statistic ->
    a number (or boolean) or a nested list of them (nested a few levels: its depth is
    bounded where it is read)."""
    path = folder.root / "meta" / "stats.json"
    stats = read_json(folder, "meta/stats.json")

    def numbers(value: object) -> bool:
        if isinstance(value, list):
            return all(numbers(v) for v in value)
        return isinstance(value, int | float)  # bool too: a flag's min and max

    if not isinstance(stats, dict) or not all(
        isinstance(s, dict) and all(numbers(v) for v in s.values()) for s in stats.values()
    ):
        raise ValueError(
            f"{path}: expected LeRobot's statistics (feature -> statistic -> numbers); "
            "refusing altered data"
        )


def check_frames(
    episode: torch.Tensor,
    step: torch.Tensor,
    book: dict[str, torch.Tensor],
    file_of: Any,
    fps: float,
    n_tasks: int,
) -> None:
    """``[N]`` frames in episode order against LeRobot's bookkeeping.

    Args:
        episode: ``[N]`` each frame's episode index.
        step: ``[N]`` 0..length-1 within each episode: what ``frame_index`` must read.
        book: ``[N]`` ``frame_index``, and ``timestamp``/``task_index`` where declared.
        file_of: frame ``i`` -> the data file holding it (for messages).
    """
    fi = book["frame_index"]
    bad = torch.nonzero(fi != step).flatten()
    if len(bad):
        i = int(bad[0])
        raise ValueError(
            f"{file_of(i)}: episode {int(episode[i])}: frame {int(step[i])} has frame_index "
            f"{int(fi[i])} (frame_index must run 0..length-1 without gaps)"
        )
    if "timestamp" in book:
        ts = book["timestamp"].double()
        gap = ts[1:] - ts[:-1]
        same = episode[1:] == episode[:-1]  # LeRobot masks the steps between episodes
        off = torch.nonzero(same & ~((gap - 1 / fps).abs() <= TOLERANCE_S)).flatten()
        if len(off):
            i = int(off[0])
            raise ValueError(
                f"{file_of(i)}: episode {int(episode[i])}: timestamps {ts[i].item():.6g} -> "
                f"{ts[i + 1].item():.6g} s at frame_index {int(fi[i])}, but fps {fps} puts frames "
                f"1/fps = {1 / fps:.6g} s apart (LeRobot's tolerance: {TOLERANCE_S} s); the "
                "declared fps or the timestamps are wrong"
            )
    if "task_index" in book:
        ti = book["task_index"]
        outside = torch.nonzero((ti < 0) | (ti >= n_tasks)).flatten()
        if len(outside):
            i = int(outside[0])
            raise ValueError(
                f"{file_of(i)}: episode {int(episode[i])}: task_index {int(ti[i])} is outside "
                f"the task table ({n_tasks} task(s))"
            )


def warn_edited(root: Path, edits: list[str], features: dict[str, dict]) -> None:
    """One warning saying what of ``meta/imitrl.json``'s record no longer applies to a
    dataset LeRobot edited in place (``edits``: :func:`verify_files`)."""
    if not edits:
        return
    rewritten = [e for e in edits if e in LEROBOT_REWRITES]
    added = [e for e in edits if e not in LEROBOT_REWRITES]
    done = [f"rewrote {rewritten}"] if rewritten else []
    if added:
        more = f" and {len(added) - 3} more" if len(added) > 3 else ""
        done.append(f"added {added[:3]}{more}")
    message = (
        f"{root}: LeRobot edited this dataset since save_lerobot wrote it ({'; '.join(done)}): "
        f"{SIDECAR}'s checksums no longer cover those files, which were checked as any "
        "LeRobot dataset is (fps and timestamps, frame_index, task_index, lengths, dtypes, "
        "NaN/inf)"
    )
    ours = [name for name in {**IMITRL_COLUMNS, **LEGACY_COLUMNS} if name in features]
    if added and ours:
        message += (
            f"; in the episodes added since, imitrl's own columns {ours} hold what LeRobot's "
            "recorder was given, not imitrl's record of DAgger rounds, executed actions, "
            "episode ids, betas and policy versions"
        )
    warnings.warn(message, UserWarning, stacklevel=3)
