"""What a LeRobot dataset's frames must satisfy before a row is returned.

LeRobot's own reader assumes these and mostly does not check them: ``fps`` is a
positive number and consecutive timestamps of an episode lie ``1 / fps`` apart within
``tolerance_s = 1e-4`` s (``LeRobotDataset(tolerance_s=1e-4)``, checked by
``check_timestamps_sync`` in ``lerobot/datasets/utils.py``); ``frame_index`` runs
0..length-1 in every episode; ``task_index`` indexes the task table. Datasets
:func:`save_lerobot` wrote also carry each file's size and SHA-256 in
``meta/imitrl.json``: a file changed since (a flipped byte, a truncation) is refused
by name, since a parquet file has no checksum of its own and a changed value would
otherwise load as data.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch

from imitrl.datasets.lerobot._layout import SIDECAR
from imitrl.fs.contained import inside

TOLERANCE_S = 1e-4
"""LeRobot's timestamp tolerance (``LeRobotDataset``'s ``tolerance_s`` default)"""


def file_digest(path: Path) -> dict[str, Any]:
    """``{"size": bytes, "sha256": hex}`` of a file, as ``meta/imitrl.json`` records it."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return {"size": path.stat().st_size, "sha256": digest.hexdigest()}


def sidecar_digest(sidecar: dict) -> str:
    """SHA-256 of ``meta/imitrl.json``'s own content (every entry but ``"digest"``), so that
    a changed key or shape in it is caught like a changed byte in the files it lists."""
    content = {k: v for k, v in sidecar.items() if k != "digest"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def verify_files(root: Path, sidecar: dict) -> None:
    """``meta/imitrl.json`` is as written (its ``"digest"``) and every file it lists is
    there, with its recorded size and SHA-256.

    A sidecar with neither ``"files"`` nor ``"digest"`` (imitrl before checksums) is not
    verified."""
    where = root / SIDECAR
    if not isinstance(sidecar, dict) or ("files" not in sidecar and "digest" not in sidecar):
        return  # a sidecar that is not an object is refused where it is read
    if sidecar.get("digest") != sidecar_digest(sidecar):
        raise ValueError(
            f"{where}: changed since save_lerobot wrote it (its content does not match its "
            "digest); refusing to load altered data"
        )
    files = sidecar.get("files")
    if not isinstance(files, dict):
        raise ValueError(f"{where}: 'files' must map file names to sizes and checksums")
    for name, recorded in files.items():
        path = inside(root, name, named_by=str(where))
        if not path.is_file():
            raise ValueError(f"{path}: file not found (listed in {where})")
        if file_digest(path) != recorded:
            raise ValueError(
                f"{path}: changed since save_lerobot wrote it (its size or SHA-256 differs from "
                f"{where}); refusing to load altered data"
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
