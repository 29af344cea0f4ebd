"""A Minari dataset's metadata and its episodes, one at a time, whatever the storage.

:func:`open_episodes` reads ``data/metadata.json`` (or, Minari < 0.5, the HDF5 file's
root attributes), parses the spaces, lists the episodes (an HDF5 group or an arrow /
parquet folder each: names only, checked for ids held twice and against
``total_episodes``) and gives an :class:`EpisodeSource` that reads any one episode on
demand (the HDF5 file stays open meanwhile). Both the in-memory load and the streamed
one (:mod:`._stream`) read through it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from imitrl.datasets.minari._arrow import list_folders, read_folder
from imitrl.datasets.minari._episodes import EpisodeList, Steps
from imitrl.datasets.minari._hdf5 import (
    MAIN_FILE,
    attrs_metadata,
    list_groups,
    open_hdf5,
    read_group,
)
from imitrl.datasets.minari._spaces import parse_space

__all__ = ["FORMATS", "METADATA_FILE", "EpisodeSource", "open_episodes"]

METADATA_FILE = "metadata.json"
FORMATS = ("hdf5", "arrow", "parquet")


def _metadata_json(path: Path) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    return meta


def _spaces(meta: dict[str, Any], where: str) -> tuple[dict, dict]:
    """The observation and action spaces the metadata declares."""
    fmt = meta.get("data_format", "hdf5")
    if fmt not in FORMATS:
        raise ValueError(f"{where}: data_format {fmt!r} is not supported (only {FORMATS})")
    for field in ("observation_space", "action_space"):
        if field not in meta:
            raise ValueError(
                f"{where}: no {field!r}; datasets that only record an env_spec are not "
                "supported (the env would have to be built to learn its spaces)"
            )
    return (
        parse_space(meta["observation_space"], f"{where}: observation_space"),
        parse_space(meta["action_space"], f"{where}: action_space"),
    )


REOPEN_EVERY = 256
"""episode groups read before the HDF5 file is opened again: HDF5 keeps state for every
object a file handle has opened (about 25 kB per episode group read, measured with h5py
3.16 / HDF5 2.0) until the file is closed, so a long pass over one handle grows with the
number of episodes"""


@dataclass
class EpisodeSource:
    """An open Minari dataset: its metadata and its episodes, read one at a time."""

    meta: dict[str, Any]
    where: str
    """the file (hdf5) or folder (arrow, parquet) messages name"""
    episodes: EpisodeList
    spaces: tuple[dict, dict]
    skipped: dict[str, str]
    """what is not loaded (per-step infos), filled in as episodes are read"""
    data_dir: Path
    h5: Any
    """the open HDF5 file, or None for arrow and parquet storage"""
    reads: int = 0
    """episodes read through this handle of the HDF5 file"""

    def __len__(self) -> int:
        return len(self.episodes)

    def read(self, e: int) -> Steps:
        """The ``e``-th episode in id order, its arrays checked against the spaces."""
        jpeg = bool(self.meta.get("jpeg_encoding", False))
        if self.h5 is None:
            fmt = self.meta["data_format"]
            return read_folder(
                self.data_dir, self.episodes, e, fmt, self.spaces, jpeg, self.skipped
            )
        if self.reads == REOPEN_EVERY:
            self.close()
            self.h5 = open_hdf5(self.data_dir / MAIN_FILE)
        self.reads += 1
        return read_group(self.h5, self.episodes, e, self.spaces, jpeg, self.skipped, self.where)

    def close(self) -> None:
        """Close the HDF5 file, if any."""
        if self.h5 is not None:
            self.h5.close()
            self.h5, self.reads = None, 0


@contextmanager
def open_episodes(data_dir: Path, skipped: dict[str, str]) -> Iterator[EpisodeSource]:
    """The dataset in ``data_dir`` (its ``data`` folder), listed and ready to read; the
    HDF5 file, if any, is closed on exit."""
    meta_path = data_dir / METADATA_FILE
    meta = _metadata_json(meta_path) if meta_path.is_file() else None
    fmt = (meta or {}).get("data_format", "hdf5")
    if fmt != "hdf5":  # arrow / parquet: metadata.json named the format
        spaces = _spaces(meta, str(meta_path))
        listing = list_folders(data_dir, fmt, meta)
        yield EpisodeSource(meta, str(data_dir), listing, spaces, skipped, data_dir, None)
        return
    where = str(data_dir / MAIN_FILE)
    h5 = open_hdf5(data_dir / MAIN_FILE)
    try:
        meta = meta if meta is not None else attrs_metadata(h5, where)
        spaces = _spaces(meta, str(meta_path) if meta_path.is_file() else where)
        try:
            listing = list_groups(h5, meta, where)
        except (OSError, KeyError, RuntimeError) as err:  # h5py's errors for a damaged file
            raise ValueError(
                f"{where}: unreadable HDF5 data ({type(err).__name__}: {err})"
            ) from err
        src = EpisodeSource(meta, where, listing, spaces, skipped, data_dir, h5)
        h5 = None
        try:
            yield src
        finally:
            src.close()
    finally:
        if h5 is not None:
            h5.close()
