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
import zipfile
from collections import deque
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import IO, Any, TypeVar

from imitrl.fs.contained import check_relative, trusted_bases

__all__ = [
    "MAX_LINKS",
    "OpenedFolder",
    "ReplacedWhileReading",
    "check_stored_zip",
    "fd_path",
    "parse_json",
    "read_whole",
]

MAX_LINKS = 40
"""symbolic links followed in one name before it is refused (the kernel's own limit)"""

_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
_FILE = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)

T = TypeVar("T")


class _Missing(ValueError):
    """No entry of that name (a walk that met ENOENT or ENOTDIR)."""


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
        links: follow symbolic links that stay inside (a hub snapshot's, a dataset a user
            assembled); False refuses every link (a folder imitrl wrote holds none).

    Raises:
        ValueError: ``root`` is not a folder.
    """

    def __init__(self, root: str | Path, *, what: str = "dataset", links: bool = True) -> None:
        self.root = Path(root)
        self.what = what
        self.links = links
        real = Path(os.path.realpath(root))
        # the widest trusted folder holding it: a hub snapshot resolves inside its repo
        bases = [b for b in trusted_bases(root) if b == real or b in real.parents]
        self.base = min(bases, key=lambda b: len(b.parts))
        self.prefix = real.relative_to(self.base).parts
        try:
            self._fd = os.open(self.base, _DIR)
        except OSError as err:
            raise ValueError(f"{root}: not a {what} folder ({err.strerror})") from None
        # the identity of the folder pinned, read off the descriptors (the name may already
        # name another folder: a writer's exchange between the open and a look-up)
        self.identity = self._pinned_identity()

    def _pinned_identity(self) -> tuple[int, int] | None:
        if not self.prefix:
            st = os.fstat(self._fd)
            return st.st_dev, st.st_ino
        try:
            st = os.stat(os.path.join(*self.prefix), dir_fd=self._fd)
        except OSError:
            return None
        return st.st_dev, st.st_ino

    def close(self) -> None:
        """Let go of the folder's descriptor."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> OpenedFolder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _folder(self, relative: object, named_by: str) -> int:
        parts = () if relative == "." else check_relative(self.root, relative, named_by=named_by)
        where = self.root.joinpath(*parts)
        return self._walk(deque([*self.prefix, *parts]), where, named_by, folder=True)

    def listdir(self, relative: object = ".", *, named_by: str = "a listing") -> list[str]:
        """The names in the folder ``relative`` (the pinned folder itself by default),
        listed through the pinned descriptor, sorted."""
        fd = self._folder(relative, named_by)
        try:
            return sorted(os.listdir(fd))
        finally:
            os.close(fd)

    def entries(
        self, relative: object = ".", *, named_by: str = "a listing"
    ) -> list[tuple[str, bool]]:
        """``(name, is a folder)`` of each entry of the folder ``relative``, through the
        pinned descriptor; [] when there is no such folder. A symbolic link counts as a
        file: :meth:`open` decides where it may lead."""
        try:
            fd = self._folder(relative, named_by)
        except _Missing:
            return []
        try:
            with os.scandir(fd) as found:
                return sorted((e.name, e.is_dir(follow_symlinks=False)) for e in found)
        finally:
            os.close(fd)

    def exists(self, relative: object, *, named_by: str = "a look-up") -> bool:
        """Whether the folder holds an entry ``relative`` (a file, a folder or a link; not
        followed at its last name)."""
        parts = check_relative(self.root, relative, named_by=named_by)
        try:
            fd = self._folder("/".join(parts[:-1]) or ".", named_by)
        except _Missing:
            return False
        try:
            os.stat(parts[-1], dir_fd=fd, follow_symlinks=False)
        except OSError:
            return False
        finally:
            os.close(fd)
        return True

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

    def _walk(self, todo: deque[str], where: Path, named_by: str, folder: bool = False) -> int:
        """The descriptor of the file (``folder``: the folder) ``todo`` leads to."""
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
                    if not self.links:
                        raise self._no_links(where, named_by)
                    links += 1
                    if links > MAX_LINKS:
                        raise ValueError(f"{where}: more than {MAX_LINKS} symbolic links")
                    todo.extendleft(reversed(self._link_parts(name, stack, where, named_by)))
                    continue
                last = not todo
                try:
                    fd = os.open(name, _FILE if last and not folder else _DIR, dir_fd=stack[-1])
                except OSError as err:
                    raise self._vanished(err, where, named_by) from None
                if last and not folder:
                    return self._regular(fd, where, named_by)
                stack.append(fd)
            if folder:
                return stack.pop()  # the last folder reached (closed by the caller)
            raise ValueError(f"{where}: {named_by} names the {self.what} folder, not a file")
        finally:
            for fd in stack:
                os.close(fd)

    def _lstat(self, name: str, dir_fd: int, where: Path, named_by: str) -> os.stat_result:
        try:
            return os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
        except OSError as err:
            raise self._vanished(err, where, named_by) from None

    def _no_links(self, where: Path, named_by: str) -> ValueError:
        real = Path(os.path.realpath(where))
        out = real != self.base and self.base not in real.parents
        kind = f"a symbolic link out of the {self.what} folder" if out else "a symbolic link"
        return ValueError(
            f"{where}: {kind}, not a regular file ({named_by} names it); a {self.what} "
            "imitrl wrote holds regular files only"
        )

    def _link_parts(self, name: str, stack: list[int], where: Path, named_by: str) -> list[str]:
        """The parts a link stands for, from where the walk is; an absolute target is
        taken from the base (refused outside it), and the stack unwound to the base."""
        try:
            target = os.readlink(name, dir_fd=stack[-1])
        except OSError as err:  # no longer a link: swapped back after the lstat
            raise ValueError(f"{where}: changed while it was opened ({err.strerror})") from None
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
        if err.errno in (errno.ENOENT, errno.ENOTDIR):
            return _Missing(f"{where}: missing ({named_by} names it)")
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


def parse_json(data: bytes | str, *, where: str, max_depth: int | None = None) -> Any:
    """``json.loads(data)``; a ValueError naming ``where`` for text that is not JSON, not
    UTF-8, has a number past Python's 4,300 digits, or is nested too deep: for the parser
    (a hostile file's recursion, which ``json.loads`` meets with a bare
    ``RecursionError``), or past ``max_depth`` levels of lists and objects (walked
    without recursion) where the caller knows its format's nesting."""
    try:
        value = json.loads(data)
    except RecursionError:
        raise ValueError(f"{where}: JSON nested too deeply to be read; refused") from None
    except ValueError as err:  # not UTF-8, not JSON, a number past Python's digit limit
        raise ValueError(f"{where}: not JSON ({err})") from None
    if max_depth is not None:
        _check_depth(value, max_depth, where)
    return value


def _check_depth(value: object, max_depth: int, where: str) -> None:
    todo: list[tuple[object, int]] = [(value, 0)]
    while todo:
        node, depth = todo.pop()
        if not isinstance(node, dict | list):
            continue
        if depth >= max_depth:
            raise ValueError(f"{where}: JSON nested more than {max_depth} levels deep; refused")
        todo.extend((v, depth + 1) for v in (node.values() if isinstance(node, dict) else node))


def read_whole(
    root: str | Path,
    load: Callable[[OpenedFolder], T],
    *,
    what: str = "dataset",
    links: bool = True,
    tries: int = 3,
) -> T:
    """``load(folder)`` on ``root`` pinned; run again on the folder now in place (up to
    ``tries`` times in all) when it failed because the folder was replaced while it ran.

    ``what`` and ``links``: as :class:`OpenedFolder` takes them.
    A load that succeeded read one folder whole through its pinned descriptor (the old
    one, if a writer exchanged it meanwhile), so its result is kept.

    Raises:
        ReplacedWhileReading: replaced during every try.
    """
    for _ in range(tries):
        with OpenedFolder(root, what=what, links=links) as folder:
            try:
                return load(folder)
            except ValueError:
                if not folder.replaced():
                    raise
    raise ReplacedWhileReading(
        f"{root}: the {what} was replaced while it was read, {tries} times in a row; "
        "try again when its writer has finished"
    )


def check_stored_zip(f: IO[bytes], where: Path | str, size: int, *, what: str) -> None:
    """Refuse a zip archive (``torch.save``'s format) that would unpack to more than its
    ``size`` bytes: one whose records are compressed (``torch.save`` stores them as they
    are) or say they hold more; checked before anything is unpacked (a zip bomb of a few
    MB would otherwise inflate to GBs). ``what``: what the archive should be, for the
    message."""
    try:
        with zipfile.ZipFile(f) as archive:
            records = archive.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, OSError, EOFError) as err:
        raise ValueError(
            f"{where}: not {what} (not the zip archive torch.save writes: {err})"
        ) from None
    packed = [r.filename for r in records if r.compress_type != zipfile.ZIP_STORED]
    unpacked = sum(r.file_size for r in records)
    if packed or unpacked > size:
        raise ValueError(
            f"{where}: records that unpack to {unpacked:_} bytes from {size:_} (compressed: "
            f"{packed[:3]}); torch.save stores them as they are, so refused before unpacking"
        )
