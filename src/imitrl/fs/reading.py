"""Reading a downloaded folder: each file opened once, by descriptor, inside the folder.

A dataset or checkpoint folder is hostile until checked, and may change while it is
read (a link swapped in for a data file, a FIFO in place of a parquet, the whole folder
replaced by a writer's exchange). :class:`OpenedFolder` pins the folder once and opens
every file relative to that descriptor, one name at a time:

* no name is followed blindly: a symbolic link is read (``readlink``) and resolved by
  hand, and refused when it leads out of the folder (or, for a hub snapshot, out of its
  repository folder, whose ``blobs/`` its links name); every ``open`` is
  ``O_NOFOLLOW``, so a link swapped in after the check fails the open instead of
  redirecting it;
* the file opened must be a regular file (checked on the descriptor): a FIFO, a device
  or a folder is refused by name, and a FIFO never blocks the open (``O_NONBLOCK``);
* a C library that wants a path (pyarrow, PyAV, h5py) is given ``/proc/self/fd/<n>``
  (:func:`fd_path`), which opens the very file already checked, whatever the name now
  points to;
* the folder's identity (device, inode) is kept: :meth:`OpenedFolder.replaced` says when
  the name now holds another folder, so a load that met a replacement in progress runs
  again on the new folder (:func:`read_whole`) rather than calling the data damaged;
  a load that finished read one folder whole, the old one or the new.

Sizes a caller reads whole (``meta/info.json``) are bounded before they are read
(:meth:`OpenedFolder.read_bytes`).
"""

from __future__ import annotations

import errno
import json
import os
import stat
from collections import deque
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import TypeVar

from imitrl.fs.contained import check_relative, trusted_bases

__all__ = [
    "MAX_LINKS",
    "OpenedFolder",
    "ReplacedWhileReading",
    "fd_path",
    "parse_json",
    "read_whole",
]

MAX_LINKS = 40
"""symbolic links followed in one name before it is refused (the kernel's own limit)"""

_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
_FILE = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)

T = TypeVar("T")


class ReplacedWhileReading(ValueError):
    """The folder was replaced by another (a writer's exchange) while it was being read,
    every time it was tried."""


def fd_path(fd: int) -> str:
    """A path that opens the file behind ``fd`` itself (``/proc/self/fd/<fd>`` on Linux,
    ``/dev/fd/<fd>`` elsewhere), for libraries that take a path."""
    return f"/proc/self/fd/{fd}" if os.path.isdir("/proc/self/fd") else f"/dev/fd/{fd}"


def _identity(path: str | Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


class OpenedFolder:
    """A folder pinned by a descriptor; its files opened inside it (module docstring).

    Args:
        root: the folder (a dataset, a checkpoint, a hub snapshot).
        what: what it is, for messages ("dataset", "checkpoint").

    Raises:
        ValueError: ``root`` is not a folder.
    """

    def __init__(self, root: str | Path, *, what: str = "dataset") -> None:
        self.root = Path(root)
        self.what = what
        real = Path(os.path.realpath(root))
        # the widest trusted folder holding it: a hub snapshot resolves inside its repo
        bases = [b for b in trusted_bases(root) if b == real or b in real.parents]
        self.base = min(bases, key=lambda b: len(b.parts))
        self.prefix = real.relative_to(self.base).parts
        try:
            self._fd = os.open(self.base, _DIR)
        except OSError as err:
            raise ValueError(f"{root}: not a {what} folder ({err.strerror})") from None
        self.identity = _identity(real)

    def close(self) -> None:
        """Let go of the folder's descriptor."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> OpenedFolder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def replaced(self) -> bool:
        """Whether ``root`` now names another folder than the one pinned (or none)."""
        return _identity(os.path.realpath(self.root)) != self.identity

    def open(self, relative: object, *, named_by: str) -> int:
        """A read-only descriptor of the regular file ``relative`` inside the folder (the
        caller closes it).

        Raises:
            ValueError: the name is not a plain relative path, leads out of the folder
                through a link, names no file, or names a FIFO, device or folder.
        """
        parts = check_relative(self.root, relative, named_by=named_by)
        where = self.root.joinpath(*parts)
        return self._walk(deque([*self.prefix, *parts]), where, named_by)

    def _walk(self, todo: deque[str], where: Path, named_by: str) -> int:
        stack = [os.dup(self._fd)]
        links = 0
        try:
            while todo:
                name = todo.popleft()
                if name in ("", "."):
                    continue
                if name == "..":
                    if len(stack) == 1:
                        raise self._outside(where, named_by)
                    os.close(stack.pop())
                    continue
                st = self._lstat(name, stack[-1], where, named_by)
                if stat.S_ISLNK(st.st_mode):
                    links += 1
                    if links > MAX_LINKS:
                        raise ValueError(f"{where}: more than {MAX_LINKS} symbolic links")
                    todo.extendleft(reversed(self._link_parts(name, stack, where, named_by)))
                    continue
                last = not todo
                try:
                    fd = os.open(name, _FILE if last else _DIR, dir_fd=stack[-1])
                except OSError as err:
                    raise self._vanished(err, where, named_by) from None
                if last:
                    return self._regular(fd, where, named_by)
                stack.append(fd)
            raise ValueError(f"{where}: {named_by} names the {self.what} folder, not a file")
        finally:
            for fd in stack:
                os.close(fd)

    def _lstat(self, name: str, dir_fd: int, where: Path, named_by: str) -> os.stat_result:
        try:
            return os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
        except OSError as err:
            raise self._vanished(err, where, named_by) from None

    def _link_parts(self, name: str, stack: list[int], where: Path, named_by: str) -> list[str]:
        """The parts a link stands for, from where the walk is; an absolute target is
        taken from the base (refused outside it), and the stack unwound to the base."""
        target = os.readlink(name, dir_fd=stack[-1])
        if not os.path.isabs(target):
            return list(PurePosixPath(target).parts)
        absolute = Path(os.path.normpath(target))
        if absolute != self.base and self.base not in absolute.parents:
            raise self._outside(where, named_by, to=target)
        while len(stack) > 1:
            os.close(stack.pop())
        return list(absolute.relative_to(self.base).parts)

    def _regular(self, fd: int, where: Path, named_by: str) -> int:
        st = os.fstat(fd)
        if stat.S_ISREG(st.st_mode):
            return fd
        os.close(fd)
        kind = "a FIFO" if stat.S_ISFIFO(st.st_mode) else "not a regular file"
        raise ValueError(
            f"{where}: {kind} ({named_by} names it); a {self.what} holds regular files only"
        )

    def _outside(self, where: Path, named_by: str, to: str | None = None) -> ValueError:
        points = f" (to {to})" if to else ""
        return ValueError(
            f"{where}: a symbolic link out of the {self.what} folder{points}; {named_by} "
            f"names it, and a {self.what} may only name its own files"
        )

    def _vanished(self, err: OSError, where: Path, named_by: str) -> ValueError:
        if self.replaced():
            return ReplacedWhileReading(f"{self.root}: replaced while reading it ({where})")
        if err.errno == errno.ELOOP:  # a link swapped in after the check
            return ValueError(f"{where}: became a symbolic link while it was opened")
        if err.errno == errno.ENOENT:
            return ValueError(f"{where}: missing ({named_by} names it)")
        return ValueError(f"{where}: cannot be read ({err.strerror}; {named_by} names it)")

    def read_bytes(self, relative: object, *, named_by: str, limit: int) -> bytes:
        """The whole file, refused (ValueError naming its size) past ``limit`` bytes before
        any of it is read."""
        fd = self.open(relative, named_by=named_by)
        with os.fdopen(fd, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > limit:
                raise ValueError(
                    f"{self.root / str(relative)}: {size:,} bytes, more than the {limit:,} "
                    f"a {named_by} may hold; refused before reading it"
                )
            data = f.read(limit + 1)
        if len(data) > limit:  # grew while it was read
            raise ValueError(f"{self.root / str(relative)}: grew past {limit:,} bytes")
        return data


def parse_json(data: bytes | str, *, where: str) -> object:
    """``json.loads(data)``; a ValueError naming ``where`` for text that is not JSON, not
    UTF-8, or nested too deep for the parser (a hostile file's recursion, which
    ``json.loads`` meets with a bare ``RecursionError``)."""
    try:
        return json.loads(data)
    except RecursionError:
        raise ValueError(f"{where}: JSON nested too deeply to be read; refused") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{where}: not JSON ({err})") from None


def read_whole(
    root: str | Path, load: Callable[[OpenedFolder], T], *, what: str = "dataset", tries: int = 3
) -> T:
    """``load(folder)`` on ``root`` pinned; run again on the folder now in place (up to
    ``tries`` times in all) when it failed because the folder was replaced while it ran.

    A load that succeeded read one folder whole through its pinned descriptor (the old
    one, if a writer exchanged it meanwhile), so its result is kept.

    Raises:
        ReplacedWhileReading: replaced during every try.
    """
    for _ in range(tries):
        with OpenedFolder(root, what=what) as folder:
            try:
                return load(folder)
            except ValueError:
                if not folder.replaced():
                    raise
    raise ReplacedWhileReading(
        f"{root}: the {what} was replaced while it was read, {tries} times in a row; "
        "try again when its writer has finished"
    )
