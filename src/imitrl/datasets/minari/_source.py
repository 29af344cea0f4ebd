"""A Minari dataset's metadata and its episodes, one at a time, whatever the storage.

:func:`open_episodes` reads ``data/metadata.json`` (or, Minari < 0.5, the HDF5 file's
root attributes), parses the spaces, lists the episodes (an HDF5 group or an arrow /
parquet folder each: names only, checked for ids held twice and against
``total_episodes``) and gives an :class:`EpisodeSource` that reads any one episode on
demand. Both the in-memory load and the streamed one (:mod:`._stream`) read through it.

Every file is opened once, by descriptor, inside the dataset folder pinned by
:class:`~imitrl.fs.reading.OpenedFolder` (a regular file, never a FIFO, never through a
link out): the HDF5 file stays open for the whole load; an arrow / parquet episode's
files are opened when it is read, and, for a streamed load (``pin=True``), kept open for
its second pass, so both passes read the very files the first one checked even if the
dataset is replaced meanwhile (up to :data:`PIN_FILES` descriptors; past them an episode
is opened again by name, inside the pinned folder).
"""

from __future__ import annotations

import os
import resource
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from imitrl.datasets.minari._arrow import EpisodeFiles, list_folders, open_episode, read_episode
from imitrl.datasets.minari._bounds import Floor
from imitrl.datasets.minari._episodes import EpisodeList, Steps
from imitrl.datasets.minari._hdf5 import (
    MAIN_FILE,
    attrs_metadata,
    list_groups,
    open_hdf5,
    read_group,
)
from imitrl.datasets.minari._spaces import parse_space
from imitrl.fs.reading import OpenedFolder, parse_json

__all__ = ["FORMATS", "METADATA_FILE", "METADATA_LIMIT", "EpisodeSource", "open_episodes"]

METADATA_FILE = "metadata.json"
FORMATS = ("hdf5", "arrow", "parquet")

METADATA_LIMIT = 32 << 20
"""bytes ``data/metadata.json`` may hold (32 MiB; a Box space's bounds are written out
value by value, a few MB for a large image space)"""

PIN_FILES = min(4096, resource.getrlimit(resource.RLIMIT_NOFILE)[0] // 2)
"""descriptors a streamed arrow / parquet load keeps open between its two passes"""


def _metadata_json(folder: OpenedFolder) -> dict[str, Any] | None:
    """``data/metadata.json``, read whole (at most :data:`METADATA_LIMIT` bytes) through
    the pinned folder; None when there is none (a Minari < 0.5 HDF5 dataset)."""
    if not os.path.lexists(folder.root / METADATA_FILE):
        return None
    where = str(folder.root / METADATA_FILE)
    data = folder.read_bytes(METADATA_FILE, named_by="the Minari layout", limit=METADATA_LIMIT)
    meta = parse_json(data, where=where)
    if not isinstance(meta, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(meta).__name__}")
    return meta


def _spaces(meta: dict[str, Any], where: str) -> tuple[dict, dict]:
    """The observation and action spaces the metadata declares."""
    fmt = meta.get("data_format", "hdf5")
    if fmt not in FORMATS:
        raise ValueError(f"{where}: data_format {fmt!r} is not supported (only {FORMATS})")
    for name in ("observation_space", "action_space"):
        if name not in meta:
            raise ValueError(
                f"{where}: no {name!r}; datasets that only record an env_spec are not "
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
    folder: OpenedFolder
    """the dataset's ``data`` folder, pinned"""
    h5_fd: int | None = None
    """the HDF5 file's descriptor (None for arrow and parquet storage)"""
    h5: Any = None
    """the open HDF5 file"""
    reads: int = 0
    """episodes read through this handle of the HDF5 file"""
    pin: bool = False
    """keep each arrow / parquet episode's files open until :meth:`close`"""
    pinned: dict[int, EpisodeFiles] = field(default_factory=dict)
    held: int = 0
    """descriptors held in ``pinned``"""
    floor: Floor = field(default_factory=Floor)
    """what the pass over the episodes may still declare beyond its files' bytes
    (:mod:`._bounds`)"""

    def __len__(self) -> int:
        return len(self.episodes)

    def new_pass(self) -> None:
        """A new pass over the episodes (a streamed load's second): it reads what the
        first read, so it starts with a whole floor again."""
        self.floor = Floor()

    def read(self, e: int) -> Steps:
        """The ``e``-th episode in id order, its arrays checked against the spaces."""
        jpeg = bool(self.meta.get("jpeg_encoding", False))
        if self.h5_fd is None:
            return self._read_folder(e, jpeg)
        if self.reads == REOPEN_EVERY:
            self.h5.close()
            self.h5, self.reads = open_hdf5(self.h5_fd, self.where), 0  # the same file
        self.reads += 1
        return read_group(
            self.h5, self.episodes, e, self.spaces, jpeg, self.skipped, self.floor, self.where
        )

    def _read_folder(self, e: int, jpeg: bool) -> Steps:
        fmt = self.meta["data_format"]
        files = self.pinned.get(e)
        if files is None:
            files = open_episode(self.folder, self.episodes.name(e), fmt)
            if self.pin and self.held + len(files.parts) <= PIN_FILES:
                self.pinned[e] = files
                self.held += len(files.parts)
        try:
            ep_id = int(self.episodes.ids[e])
            return read_episode(files, ep_id, fmt, self.spaces, jpeg, self.skipped, self.floor)
        finally:
            if self.pinned.get(e) is not files:
                files.close()

    def close(self) -> None:
        """Close the HDF5 file and every descriptor held."""
        if self.h5 is not None:
            self.h5.close()
            self.h5 = None
        if self.h5_fd is not None:
            os.close(self.h5_fd)
            self.h5_fd = None
        for files in self.pinned.values():
            files.close()
        self.pinned, self.held = {}, 0


@contextmanager
def open_episodes(
    folder: OpenedFolder, skipped: dict[str, str], *, pin: bool = False
) -> Iterator[EpisodeSource]:
    """The dataset in ``folder`` (its ``data`` folder, pinned), listed and ready to read;
    every file it opened is closed on exit. ``pin``: keep arrow / parquet episodes' files
    open for a second pass (module docstring)."""
    meta = _metadata_json(folder)
    meta_where = str(folder.root / METADATA_FILE)
    fmt = (meta or {}).get("data_format", "hdf5")
    if fmt != "hdf5":  # arrow / parquet: metadata.json named the format
        assert meta is not None  # without it, the format is hdf5
        spaces = _spaces(meta, meta_where)
        listing = list_folders(folder, fmt, meta)
        src = EpisodeSource(meta, str(folder.root), listing, spaces, skipped, folder, pin=pin)
        try:
            yield src
        finally:
            src.close()
        return
    where = str(folder.root / MAIN_FILE)
    fd = folder.open(MAIN_FILE, named_by="the Minari layout")
    h5 = None
    try:
        h5 = open_hdf5(fd, where)
        spaces_where = meta_where if meta is not None else where
        meta = meta if meta is not None else attrs_metadata(h5, where)
        spaces = _spaces(meta, spaces_where)
        try:
            listing = list_groups(h5, meta, where)
        except (OSError, KeyError, RuntimeError) as err:  # h5py's errors for a damaged file
            raise ValueError(
                f"{where}: unreadable HDF5 data ({type(err).__name__}: {err})"
            ) from err
    except BaseException:
        if h5 is not None:
            h5.close()
        os.close(fd)
        raise
    src = EpisodeSource(meta, where, listing, spaces, skipped, folder, h5_fd=fd, h5=h5)
    try:
        yield src
    finally:
        src.close()
