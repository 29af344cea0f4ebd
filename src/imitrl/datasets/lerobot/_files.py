"""The files of one LeRobot load, read through its pinned folder.

:func:`~imitrl.datasets.lerobot.load_lerobot` reads a dataset through one
:class:`~imitrl.fs.reading.OpenedFolder` (and runs again when a writer replaced the
folder meanwhile: :func:`~imitrl.fs.reading.read_whole`). Every file is opened by
descriptor inside that folder, once per read, and must be a regular file: a symbolic
link out of the folder or a FIFO is refused by name, never followed or waited on, and a
link swapped in after a check fails the open instead of redirecting it. Libraries that
want a path (pyarrow, PyAV) get the descriptor's own (:func:`opened`).

The folders a layout lists (``data/chunk-*``, ``meta/episodes/chunk-*``, what LeRobot
adds under ``data``, ``videos``, ...) are listed through the pinned descriptor too
(:meth:`~imitrl.fs.reading.OpenedFolder.entries`): a listing of the replacement is never
mixed with reads of the original.

Metadata read whole is bounded before it is read (:data:`READ_LIMITS`), and its JSON
nesting too (:data:`MAX_JSON_DEPTH`): a hostile file is refused with one ValueError
naming it, not met with a MemoryError or a RecursionError.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Any

from imitrl.datasets._common import open_in, read_in
from imitrl.fs.reading import OpenedFolder, fd_path, parse_json

READ_LIMITS = {
    "meta/info.json": 16 << 20,
    "meta/imitrl.json": 64 << 20,
    "meta/stats.json": 64 << 20,
    "meta/tasks.jsonl": 256 << 20,
    "meta/episodes.jsonl": 256 << 20,
}
"""bytes each metadata file read whole may hold (refused past it before it is read); a
real one holds a few kilobytes (``info.json``) to tens of megabytes (``episodes.jsonl``
of 100,000 episodes)"""

MAX_JSON_DEPTH = 32
"""nesting of LeRobot's JSON metadata: ``info.json``'s features nest 4 deep,
``stats.json``'s statistics 2 deep plus a feature's dimensions (at most 5)"""

MAX_LIST_DEPTH = 8
"""folders below ``data/``, ``videos/``, ``images/`` or ``meta/episodes/`` a listing
descends (LeRobot's own layout: ``videos/<camera>/chunk-000/file-000.mp4``, 3)"""

LAYOUT = "the LeRobot layout"
"""who names the files every dataset has (``meta/info.json``), for messages"""

_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)


def parse_bounded(data: bytes, where: str) -> Any:
    """:func:`~imitrl.fs.reading.parse_json` with LeRobot's nesting bound
    (:data:`MAX_JSON_DEPTH`)."""
    return parse_json(data, where=where, max_depth=MAX_JSON_DEPTH)


def read_json(folder: OpenedFolder, relative: str) -> Any:
    """The JSON metadata file ``relative`` (a key of :data:`READ_LIMITS`), size and nesting
    bounded; ValueError naming it when absent, too large, not JSON or too deep."""
    where = folder.root / relative
    if not holds(folder, relative):
        required = " (meta/info.json is required)" if relative == "meta/info.json" else ""
        raise ValueError(f"{where} not found: not a LeRobot dataset{required}")
    data = read_in(folder, relative, named_by=LAYOUT, limit=READ_LIMITS[relative])
    return parse_bounded(data, str(where))


def jsonl_lines(folder: OpenedFolder, relative: str, *, why: str) -> list[tuple[int, bytes]]:
    """``(line number, line)`` of each non-empty line of the JSON-lines file ``relative``
    (a key of :data:`READ_LIMITS`), its size bounded, not parsed yet (a caller may count
    them first); ``why`` says what it lists, for a missing file."""
    if not holds(folder, relative):
        raise ValueError(f"{folder.root / relative} not found ({why})")
    data = read_in(folder, relative, named_by=LAYOUT, limit=READ_LIMITS[relative])
    return [(i + 1, line) for i, line in enumerate(data.splitlines()) if line.strip()]


def parse_lines(lines: list[tuple[int, bytes]], *, where: Path) -> list[Any]:
    """Each line of :func:`jsonl_lines` parsed, its nesting bounded; a ValueError naming
    ``where`` and the line otherwise."""
    return [parse_bounded(line, f"{where}:{number}") for number, line in lines]


def read_jsonl(folder: OpenedFolder, relative: str, *, why: str) -> list[Any]:
    """The entries of the JSON-lines file ``relative``: :func:`jsonl_lines`, parsed."""
    lines = jsonl_lines(folder, relative, why=why)
    return parse_lines(lines, where=folder.root / relative)


@contextmanager
def opened(folder: OpenedFolder, relative: str, *, named_by: str) -> Iterator[str]:
    """A path (``/proc/self/fd/<n>``) to the regular file ``relative`` of the folder, open
    by descriptor for the block: a library opening it reads the very file checked."""
    fd = open_in(folder, relative, named_by=named_by)
    try:
        yield fd_path(fd)
    finally:
        os.close(fd)


def holds(folder: OpenedFolder, relative: str) -> bool:
    """Whether the pinned folder holds an entry ``relative`` (a file, or a link the open
    then follows only inside the folder)."""
    return folder.exists(relative, named_by=LAYOUT)


def list_files(folder: OpenedFolder, top: str, *, suffix: str, depth: int | None) -> list[str]:
    """The files under ``top`` (relative names, sorted) whose names end with ``suffix``:
    ``depth`` folders below it (``data/*/*.parquet`` is depth 1), or any depth (None) up to
    :data:`MAX_LIST_DEPTH` (a folder nested deeper is refused)."""
    out: list[str] = []
    todo = [(top, 0)]
    while todo:
        where, level = todo.pop()
        for name, is_dir in folder.entries(where, named_by=LAYOUT):
            if is_dir and depth is None and level >= MAX_LIST_DEPTH:
                raise ValueError(
                    f"{folder.root / where / name}: a folder nested more than "
                    f"{MAX_LIST_DEPTH} deep under {top}/; LeRobot's layout nests 3 (refused)"
                )
            if is_dir and (depth is None or level < depth):
                todo.append((f"{where}/{name}", level + 1))
            elif not is_dir and name.endswith(suffix) and (depth is None or level == depth):
                out.append(f"{where}/{name}")
    return sorted(out, key=lambda name: PurePosixPath(name).parts)
