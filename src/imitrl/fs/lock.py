"""One writer per path: an exclusive lock beside the path (:func:`exclusive`).

The lock is ``flock`` on the file ``.<name>.imitrl-lock`` in the path's parent folder:
the kernel drops it when its holder dies, so a killed writer never leaves a stale lock.
A second process (or a second thread of this one) that asks for a held lock is refused
at once with a ``ValueError`` naming the holder; nobody waits. Within one thread the
lock is re-entrant, so a run that holds its checkpoint folder for its whole length
(:func:`imitrl.algorithms.dagger`) can publish into it after every round.

Where ``fcntl`` is missing (not POSIX), the lock file is created with ``O_EXCL``; a
killed writer's lock file must then be removed by hand, and the message says so.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

__all__ = ["LOCK_SUFFIX", "absolute", "exclusive", "lock_file"]

LOCK_SUFFIX = ".imitrl-lock"

_held: dict[Path, tuple[int, int]] = {}
"""locked path -> (holding thread, depth), for this process"""
_guard = threading.Lock()


def absolute(path: str | Path) -> Path:
    """``path`` made absolute with ``~`` expanded and ``..`` folded (symbolic links are not
    followed); ValueError for a path that names no folder (``/``, ``.``)."""
    target = Path(os.path.abspath(os.path.expanduser(path)))
    if target.name in ("", ".", ".."):
        raise ValueError(f"{path!r} names no directory that can be written (resolved: {target})")
    return target


def lock_file(target: Path) -> Path:
    """Where the lock of ``target`` lives: ``.<name>.imitrl-lock`` beside it."""
    return target.parent / f".{target.name}{LOCK_SUFFIX}"


@contextmanager
def exclusive(path: str | Path, *, what: str = "written") -> Iterator[Path]:
    """Hold the lock of ``path`` (see the module docstring); yields the absolute path.

    Args:
        path: the file or folder to be written (its parent folder is created).
        what: the verb of the refusal, "``path`` is being <what> by another process".

    Raises:
        ValueError: another process or thread holds it.
    """
    target = absolute(path)
    me = threading.get_ident()
    with _guard:
        holder = _held.get(target)
        if holder is not None:
            if holder[0] != me:
                raise ValueError(
                    f"{target} is being {what} by another thread of this process; one "
                    "writer per path"
                )
            _held[target] = (me, holder[1] + 1)
    if holder is not None:
        try:
            yield target
        finally:
            with _guard:
                _held[target] = (me, _held[target][1] - 1)
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(target, what)
    with _guard:
        _held[target] = (me, 1)
    try:
        yield target
    finally:
        with _guard:
            del _held[target]
        _release(target, fd)


def _acquire(target: Path, what: str) -> int:
    lock = lock_file(target)
    if fcntl is None:  # pragma: no cover - not POSIX
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise ValueError(
                f"{target} is being {what} by another process ({lock} exists; if nothing is "
                "running, a killed writer left it: remove it)"
            ) from None
    else:
        while True:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise ValueError(
                    f"{target} is being {what} by another process ({holder}, holding {lock}); "
                    "one writer per path"
                ) from None
            try:  # the previous holder may have removed the file before we locked it: retry
                if os.stat(lock).st_ino == os.fstat(fd).st_ino:
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
