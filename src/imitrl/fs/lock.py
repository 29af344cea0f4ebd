"""One writer per path: an exclusive lock beside the path (:func:`exclusive`).

The lock is ``flock`` on the file ``.<name>.imitrl-lock`` in the path's parent folder:
the kernel drops it when its holder dies, so a killed writer never leaves a stale lock.
A second process (or a second thread of this one) that asks for a held lock is refused
at once with a ``ValueError`` naming the holder, unless it asked to wait (``wait``: a
download into a shared cache waits for the one in progress). Within one thread the
lock is re-entrant, so a run that holds its checkpoint folder for its whole length
(:func:`imitrl.algorithms.dagger`) can publish into it after every round.

The lock file is opened without following a link (``O_NOFOLLOW``) and checked on the
opened descriptor: a symbolic link, a hard link or a FIFO planted at its name is refused
naming it, and nothing is written through it (:mod:`imitrl.fs.files`).

Where ``fcntl`` is missing (not POSIX), the lock file is created with ``O_EXCL``; a
killed writer's lock file must then be removed by hand, and the message says so.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

from imitrl.fs.files import WRITE_REFUSALS, PlantedLinkError, check_regular, make_folder
from imitrl.fs.write_errors import reporting_disk_full

fcntl: ModuleType | None  # None where it is missing (not POSIX)
try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

__all__ = ["LOCK_SUFFIX", "absolute", "exclusive", "lock_file"]

LOCK_SUFFIX = ".imitrl-lock"

_held: dict[Path, tuple[int, int]] = {}
"""locked path -> (holding thread, depth), for this process"""
_guard = threading.Lock()
_PATH_MAX = os.pathconf("/", "PC_PATH_MAX") if hasattr(os, "pathconf") else 1024
_NAME_MAX = os.pathconf("/", "PC_NAME_MAX") if hasattr(os, "pathconf") else 255
_BESIDE = 40
"""bytes a name may grow by beside it (``.<name>.imitrl-tmp-<hex>``, ``.imitrl-lock``)"""
_POLL_S = 0.05
"""seconds between two tries of a held lock, for a caller that waits"""


def absolute(path: str | Path) -> Path:
    """``path`` made absolute with ``~`` expanded and ``..`` folded (symbolic links are not
    followed); ValueError for a path that names no folder (``/``, ``.``)."""
    target = Path(os.path.abspath(os.path.expanduser(path)))
    if target.name in ("", ".", ".."):
        raise ValueError(f"{path!r} names no directory that can be written (resolved: {target})")
    longest_name = max(len(os.fsencode(part)) for part in target.parts)
    if len(os.fsencode(target)) + _BESIDE > _PATH_MAX or longest_name + _BESIDE > _NAME_MAX:
        raise ValueError(
            f"{str(path)[:80]}...: a path of {len(os.fsencode(target)):,} bytes in "
            f"{len(target.parts):,} parts (longest name {longest_name:,} bytes); this system "
            f"writes paths up to {_PATH_MAX:,} bytes and names up to {_NAME_MAX} (less "
            f"{_BESIDE} for the files imitrl keeps beside it): choose a shorter one"
        )
    return target


def lock_file(target: Path) -> Path:
    """Where the lock of ``target`` lives: ``.<name>.imitrl-lock`` beside it."""
    return target.parent / f".{target.name}{LOCK_SUFFIX}"


@contextmanager
def exclusive(
    path: str | Path, *, what: str = "written", wait: float | None = 0.0
) -> Iterator[Path]:
    """Hold the lock of ``path`` (see the module docstring); yields the absolute path.

    Args:
        path: the file or folder to be written (its parent folder is created).
        what: the verb of the refusal, "``path`` is being <what> by another process".
        wait: seconds to wait for a holder to finish (0: refused at once, the default for
            writers; None: as long as it takes, as a download into a shared cache waits).

    Raises:
        ValueError: another process or thread holds it (past ``wait``).
        imitrl.fs.files.PlantedLinkError: a symbolic link, a hard link or a special file
            stands where the lock file goes (nothing is written through it).
    """
    target = absolute(path)
    me = threading.get_ident()
    deadline = None if wait is None else time.monotonic() + wait
    while True:
        with _guard:
            holder = _held.get(target)
            if holder is None or holder[0] == me:
                _held[target] = (me, 1 if holder is None else holder[1] + 1)
                break
        if deadline is not None and time.monotonic() >= deadline:
            raise ValueError(
                f"{target} is being {what} by another thread of this process; one writer per path"
            )
        time.sleep(_POLL_S)
    if holder is not None:
        try:
            yield target
        finally:
            with _guard:
                _held[target] = (me, _held[target][1] - 1)
        return
    try:
        with reporting_disk_full(target, what="files", left="nothing was written"):
            make_folder(target.parent)
            try:
                fd = _acquire(target, what, deadline)
            except OSError as err:
                if err.errno in WRITE_REFUSALS:
                    raise
                raise ValueError(
                    f"{target} cannot be written there ({err.strerror}: {err.filename})"
                ) from None
    except BaseException:
        with _guard:
            del _held[target]
        raise
    try:
        yield target
    finally:
        with _guard:
            del _held[target]
        _release(target, fd)


def _open_lock(lock: Path, flags: int) -> int:
    """The lock file, opened without following a link; only a regular file of one name."""
    try:
        fd = os.open(lock, flags | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o666)
    except OSError as err:
        if err.errno == errno.ELOOP or (err.errno == errno.EEXIST and lock.is_symlink()):
            raise PlantedLinkError(
                f"{lock}: a symbolic link stands where imitrl keeps its lock (it points to "
                f"{_target(lock)}); imitrl never writes through a link: remove it"
            ) from None
        raise
    check_regular(fd, lock, "its lock")
    return fd


def _target(link: Path) -> str:
    try:
        return os.readlink(link)
    except OSError:
        return "?"


def _acquire(target: Path, what: str, deadline: float | None) -> int:
    lock = lock_file(target)
    if fcntl is None:  # pragma: no cover - not POSIX
        try:
            fd = _open_lock(lock, os.O_RDWR | os.O_CREAT | os.O_EXCL)
        except FileExistsError:
            raise ValueError(
                f"{target} is being {what} by another process ({lock} exists; if nothing is "
                "running, a killed writer left it: remove it)"
            ) from None
    else:
        told = False
        while True:
            fd = _open_lock(lock, os.O_RDWR | os.O_CREAT)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                if deadline is not None and time.monotonic() >= deadline:
                    raise ValueError(
                        f"{target} is being {what} by another process ({holder}, holding "
                        f"{lock}); one writer per path"
                    ) from None
                if not told:
                    print(
                        f"imitrl: waiting for {holder} ({target} is being {what})", file=sys.stderr
                    )
                    told = True
                time.sleep(_POLL_S)
                continue
            try:  # the previous holder may have removed the file before we locked it: retry
                if os.stat(lock, follow_symlinks=False).st_ino == os.fstat(fd).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"pid {os.getpid()}".encode())
    return fd


def _release(target: Path, fd: int) -> None:
    try:
        os.unlink(lock_file(target))  # while still holding it (see the retry above)
    except FileNotFoundError:
        pass
    os.close(fd)
