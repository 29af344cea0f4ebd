"""Put a directory in place atomically and exclusively (:func:`publishing`).

Every folder this library writes as a whole (a LeRobot or Minari dataset, a buffer or
DAgger checkpoint, a job's output) is written into a fresh sibling of its destination,
``.<name>.imitrl-tmp-<random>``, and only then moved into place, so a reader never sees
half of it and an exception, a full disk or a kill at any point leaves the destination
as it was. The steps, under the path's exclusive lock (:func:`imitrl.fs.lock.exclusive`)::

    1. leftovers of a killed writer are sorted out (see below)
    2. the destination is checked: absent, an empty directory (``empty_ok``), or
       (``overwrite``) a directory ``replaceable`` accepts
    3. the caller writes into the temporary directory
    4. the temporary directory is fsynced, the destination checked again, then
       absent destination: rename(tmp, dest)
       existing one:       renameat2(tmp, dest, RENAME_EXCHANGE), then the old one,
                           now at tmp, is removed
    5. the parent directory is fsynced

The exchange (Linux) swaps both names in one step: a reader at any instant finds the
old directory or the new one, never none. Where the file system or the platform does
not offer it, the old directory is renamed aside to ``.<name>.imitrl-old-<hex>`` for
the instant between two renames (and moved back if the second fails); a reader that
finds nothing in that instant is told where the old one is.

Of several writers of one path, one holds the lock and the others are refused at once
(ValueError naming the holder); a writer of a path that exists (without
``overwrite``) is refused too, so of writers started together exactly one succeeds.
Leftovers of a killed writer are handled by the next writer, under the lock: a
temporary directory (an unfinished write, or the old directory an exchange had not yet
removed) is removed; an ``old`` directory beside a missing destination is the previous
one caught between the two renames and is moved back; beside a present destination it
is what a finished swap had not yet removed, and is removed. Each is named in a warning.

The temporary directory is made with the user's umask (not ``mkdtemp``'s 0700), so the
published directory has the permissions any other program's output would have there.

The working directory, or any directory holding it, is never replaced.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import secrets
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from imitrl.fs.files import new_sibling, remove_tree
from imitrl.fs.lock import absolute, exclusive
from imitrl.fs.write_errors import reporting_disk_full

__all__ = ["OLD", "TMP", "exchange", "fsync_dir", "publishing", "recover", "swap_in"]

TMP = ".imitrl-tmp-"
OLD = ".imitrl-old-"


def _refuse_working_directory(target: Path, given: str | Path) -> None:
    cwd = Path.cwd().resolve()
    resolved = target.resolve()
    if resolved == cwd or resolved in cwd.parents:
        raise ValueError(
            f"{given!r} is the working directory or holds it ({resolved}); it is never "
            "written over: choose a new directory"
        )


def _leftovers(target: Path, mark: str) -> list[Path]:
    pattern = re.compile(re.escape(f".{target.name}{mark}") + r"[A-Za-z0-9_]+")
    return sorted(p for p in target.parent.iterdir() if pattern.fullmatch(p.name))


def recover(target: Path) -> None:
    """Finish or undo what a killed writer of ``target`` left (the lock is held)."""
    done: list[str] = []
    for tmp in _leftovers(target, TMP):
        remove_tree(tmp)  # a link planted at the name is refused (PlantedLinkError)
        done.append(f"removed {tmp.name} (an unfinished write, or what a finished one replaced)")
    olds = _leftovers(target, OLD)
    if olds and not os.path.lexists(target):
        if olds[0].is_symlink():
            remove_tree(olds[0])  # refused, naming it
        if len(olds) > 1:
            raise ValueError(
                f"{target} is missing and several earlier versions lie beside it "
                f"({[p.name for p in olds]}); move the right one back to {target.name} by hand"
            )
        os.rename(olds[0], target)
        done.append(f"moved {olds[0].name} back to {target.name} (a replacement cut short)")
    else:
        for old in olds:
            remove_tree(old)
            done.append(f"removed {old.name} (replaced by a finished write)")
    if done:
        warnings.warn(
            f"{target.parent}: a killed writer's leftovers: " + "; ".join(done),
            UserWarning,
            stacklevel=6,  # the caller of the writer
        )


def _check_destination(
    target: Path,
    given: str | Path,
    overwrite: bool,
    replaceable: Callable[[Path], None],
    empty_ok: bool,
) -> None:
    if not os.path.lexists(target):
        return
    if target.is_symlink() or not target.is_dir():
        kind = "a symbolic link" if target.is_symlink() else "not a directory"
        raise ValueError(f"{given} is {kind}; only a directory written by imitrl is replaced")
    if empty_ok and not os.listdir(target):
        return  # an empty directory: nothing to lose
    if not overwrite:
        raise ValueError(f"{given} exists; pass overwrite=True to replace it")
    replaceable(target)


def fsync_dir(path: Path) -> None:
    """Make ``path``'s entries (names created or renamed in it) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def exchange(a: Path, b: Path) -> bool:
    """Swap two directory entries atomically (Linux ``renameat2(RENAME_EXCHANGE)``);
    False where the platform or file system does not offer it."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), str(b))


def swap_in(tmp: Path, target: Path) -> None:
    """``tmp`` becomes ``target``; an existing ``target`` ends at ``tmp`` (exchange) or is
    moved aside and removed (two renames; moved back if the second fails)."""
    if not os.path.lexists(target):
        try:
            os.rename(tmp, target)  # atomic; fails (ENOTEMPTY) rather than merge into a dir
            return
        except OSError as err:
            if err.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
    if exchange(tmp, target):
        return  # tmp now holds the old directory: the caller removes it
    old = target.parent / f".{target.name}{OLD}{secrets.token_hex(6)}"
    os.rename(target, old)
    try:
        os.rename(tmp, target)
    except BaseException:
        os.rename(old, target)
        raise
    remove_tree(old)


@contextmanager
def publishing(
    path: str | Path,
    *,
    overwrite: bool,
    replaceable: Callable[[Path], None],
    what: str = "a dataset",
    empty_ok: bool = False,
) -> Iterator[Path]:
    """A fresh directory to write into; it becomes ``path`` when the block ends without
    error, atomically and under an exclusive lock (see the module docstring).

    Args:
        path: the destination directory (its parents are created).
        overwrite: replace an existing, non-empty ``path``, which ``replaceable`` must accept.
        replaceable: raises ValueError (saying why) unless the directory may be replaced.
        what: what is written, for messages ("a dataset", "a buffer checkpoint").
        empty_ok: an existing empty directory is written over without ``overwrite``
            (a checkpoint's rule; a dataset asks for ``overwrite`` even then).

    Raises:
        ValueError: ``path`` is (or holds) the working directory; exists, is not empty and
            not ``overwrite``; is not a directory ``replaceable`` accepts; another process
            is writing it; a killed writer left something that cannot be sorted out.
        imitrl.fs.DiskFullError: the file system filled up (``path`` is as it was).
    """
    target = absolute(path)
    _refuse_working_directory(target, path)
    with exclusive(target), reporting_disk_full(target, what=what):
        recover(target)
        _check_destination(target, path, overwrite, replaceable, empty_ok)
        tmp = new_sibling(target, TMP)  # the user's umask, as the published folder keeps
        try:
            yield tmp
            fsync_dir(tmp)
            _check_destination(target, path, overwrite, replaceable, empty_ok)  # others
            swap_in(tmp, target)
            fsync_dir(target.parent)
        finally:
            if tmp.exists():
                remove_tree(tmp)
