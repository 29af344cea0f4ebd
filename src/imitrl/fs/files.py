"""Creating files and folders without following links, with the user's permissions.

Every file or folder imitrl creates outside a staging folder it made itself (a lock, a
hub cache entry, ``eval.json``, a staging folder beside its destination) is created
here, so that a planted symbolic link (``results/.bc.imitrl-lock -> ~/.ssh/...``) can
never make imitrl write through it:

* a new file is opened ``O_CREAT | O_EXCL | O_NOFOLLOW``: it did not exist, and a link
  standing at its name is refused, naming it (:func:`create_file`);
* a file that replaces another is written whole to a fresh sibling and renamed over it
  (:func:`replace_file`): ``rename`` replaces a link itself, never its target;
* a folder is made with ``mkdir(path, 0o777)``, which fails on a link and takes the
  user's ``umask`` like every other program's output (:func:`make_folder`,
  :func:`new_sibling`): a dataset saved into a shared folder is readable by the group
  when the umask says so (``tempfile.mkdtemp`` made them 0700).

A refusal is a :class:`PlantedLinkError` (a ``ValueError``: bad input, one line on the
command line) naming the link and where it points.
"""

from __future__ import annotations

import errno
import os
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "WRITE_REFUSALS",
    "PlantedLinkError",
    "check_plain_tree",
    "check_regular",
    "create_file",
    "make_folder",
    "new_sibling",
    "open_own",
    "remove_tree",
    "replace_file",
    "walk_tree",
]

WRITE_REFUSALS = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EACCES,
                   errno.EPERM, errno.EROFS}  # fmt: skip
"""errors :mod:`imitrl.fs.write_errors` names (a full disk, a folder that cannot be written)"""

_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)


class PlantedLinkError(ValueError):
    """A symbolic link (or another special file) stands where imitrl writes a file."""


def _planted(path: Path, what: str) -> PlantedLinkError:
    try:
        points = f" (it points to {os.readlink(path)})"
    except OSError:
        points = ""
    return PlantedLinkError(
        f"{path}: a symbolic link stands where imitrl writes {what}{points}; imitrl never "
        "writes through a link: remove it, or choose another folder"
    )


def check_regular(fd: int, path: Path, what: str) -> os.stat_result:
    """``fstat(fd)`` when it is a regular file with one name; PlantedLinkError (the fd is
    closed) when it is a FIFO, a device, a folder or a hard link shared with another name
    (which could be a file outside the folder)."""
    st = os.fstat(fd)
    if stat.S_ISREG(st.st_mode) and st.st_nlink <= 1:
        return st
    os.close(fd)
    kind = "a hard link to another file" if stat.S_ISREG(st.st_mode) else "not a regular file"
    raise PlantedLinkError(
        f"{path}: {kind} stands where imitrl writes {what}; imitrl writes only its own "
        "regular files: remove it, or choose another folder"
    )


def create_file(
    path: str | Path, *, what: str = "a file", mode: int = 0o666, readable: bool = False
) -> int:
    """Open a new file for writing (``O_EXCL | O_NOFOLLOW``; ``readable``: for reading
    too); returns its descriptor.

    Raises:
        PlantedLinkError: a symbolic link stands at ``path``.
        FileExistsError: a file (or folder) already has that name.
    """
    path = Path(path)
    flags = (_CREATE & ~os.O_WRONLY) | os.O_RDWR if readable else _CREATE
    try:
        return os.open(path, flags, mode)
    except FileExistsError:
        if path.is_symlink():
            raise _planted(path, what) from None
        raise
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise _planted(path, what) from None
        raise


def replace_file(
    path: str | Path, data: bytes | str, *, what: str = "a file", durable: bool = True
) -> None:
    """Write ``data`` to ``path`` whole: into a fresh sibling (:func:`create_file`),
    flushed to disk (``durable``; False where the file describes data that is not flushed
    either, a disk buffer's row count), then renamed over ``path`` (a link at ``path`` is
    replaced, its target never written). A reader finds the old file or the new one, never
    half of one."""
    path = Path(path)
    if isinstance(data, str):
        data = data.encode()
    tmp = path.with_name(f".{path.name}.imitrl-tmp-{secrets.token_hex(6)}")
    fd = create_file(tmp, what=what)
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data)
            out.flush()
            if durable:
                os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def open_own(path: str | Path, *, what: str = "a file") -> int:
    """Open (or create) ``path`` for reading and appending without following a link, and
    only when it is a regular file of one name (:func:`check_regular`): a lock file kept
    in a folder that may hold planted links."""
    path = Path(path)
    flags = os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | os.O_NONBLOCK
    try:
        fd = os.open(path, flags | getattr(os, "O_CLOEXEC", 0), 0o666)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise _planted(path, what) from None
        if err.errno == errno.EISDIR:  # a folder planted at the name (was a raw OSError)
            raise ValueError(f"{path} is a folder where {what} should be a file") from None
        raise
    check_regular(fd, path, what)
    return fd


def make_folder(path: str | Path) -> Path:
    """``path`` and its missing parents as folders (the user's umask); an existing folder
    is kept. ValueError when ``path`` or a folder above it is a file, or the system cannot
    make it (``/proc``); PlantedLinkError when it is a link to a folder (a dangling link
    makes ``mkdir`` fail too); a full disk or a read-only folder raises its ``OSError``."""
    path = Path(path)
    if path.is_symlink():
        raise _planted(path, "a folder")
    missing = []
    for folder in (path, *path.parents):  # made top down, without recursion: a path may
        if os.path.isdir(folder):  # be thousands of folders deep
            break
        missing.append(folder)
    for folder in reversed(missing):
        try:
            os.mkdir(folder, 0o777)
        except FileExistsError:
            if not os.path.isdir(folder):
                raise ValueError(
                    f"{folder} is a file, not a folder: {path} cannot be made"
                ) from None
        except OSError as err:
            if err.errno in WRITE_REFUSALS:
                raise  # a full disk or a read-only folder: imitrl.fs.write_errors names it
            raise ValueError(f"cannot create the folder {folder} ({err.strerror})") from None
    return path


def new_sibling(target: Path, mark: str) -> Path:
    """A new, empty folder ``.<name><mark><random>`` beside ``target`` (the user's umask;
    ``mkdir`` fails rather than reuse a name or follow a link)."""
    for _ in range(100):
        candidate = target.parent / f".{target.name}{mark}{secrets.token_hex(6)}"
        try:
            os.mkdir(candidate, 0o777)
        except FileExistsError:
            continue
        return candidate
    raise FileExistsError(errno.EEXIST, "no free name for a staging folder", str(target))


def walk_tree(root: str | Path) -> Iterator[tuple[Path, os.stat_result]]:
    """Every entry under ``root`` (not ``root`` itself), with its ``lstat``, parents before
    children; links are reported, never followed; an entry removed while it is walked is
    passed over. Without recursion: a tree thousands of
    folders deep (a hostile download) is walked like any other (``os.walk`` and
    ``shutil.rmtree`` recurse per folder on Python 3.11)."""
    todo = [Path(root)]
    while todo:
        folder = todo.pop()
        try:
            with os.scandir(folder) as entries:
                found = sorted(entries, key=lambda e: e.name)
        except (FileNotFoundError, NotADirectoryError):
            continue  # gone (or replaced) since it was listed: nothing left to walk
        for entry in found:
            path = Path(entry.path)
            try:
                st = entry.stat(follow_symlinks=False)
            except FileNotFoundError:
                continue  # removed since it was listed
            yield path, st
            if stat.S_ISDIR(st.st_mode):
                todo.append(path)


def remove_tree(root: str | Path) -> None:
    """Remove ``root`` and everything under it, without recursion (:func:`walk_tree`) and
    without following a link (a link is removed itself, never its target); a missing
    ``root`` is fine, a ``root`` that is a link is refused (:class:`PlantedLinkError`)."""
    root = Path(root)
    if not os.path.lexists(root):
        return
    if root.is_symlink():
        raise _planted(root, "a folder it removes")
    folders = [root]
    for path, st in walk_tree(root):
        if stat.S_ISDIR(st.st_mode):
            folders.append(path)
        else:
            path.unlink()
    for folder in reversed(folders):  # children before their parents
        os.rmdir(folder)


def check_plain_tree(root: str | Path, *, what: str) -> None:
    """Refuse (:class:`PlantedLinkError`, naming it) a tree under ``root`` that holds a
    symbolic link, a hard link to another file, a FIFO or a device: a folder imitrl wrote
    holds plain folders and regular files only, so one it continues (a run resumed, a
    finished run copied) may be written without any write going through a link."""
    for path, st in walk_tree(root):
        if stat.S_ISDIR(st.st_mode) or (stat.S_ISREG(st.st_mode) and st.st_nlink <= 1):
            continue
        if stat.S_ISLNK(st.st_mode):
            raise _planted(path, what)
        kind = "a hard link to another file" if stat.S_ISREG(st.st_mode) else "a special file"
        raise PlantedLinkError(
            f"{path}: {kind} inside {what}; a folder imitrl wrote holds regular files only: "
            "remove it, or choose another folder"
        )
