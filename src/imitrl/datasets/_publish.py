"""Put a directory in place atomically and exclusively (:func:`publishing`).

A dataset is written whole into a fresh sibling of its destination,
``.<name>.imitrl-tmp-<random>``, and only then renamed into place, so a reader never
sees half a dataset and an exception or a kill at any point leaves the destination
as it was. The steps, under an exclusive lock on ``.<name>.imitrl-lock`` (``flock``:
the kernel drops it when its holder dies, so a killed writer leaves no stale lock)::

    1. leftovers of a killed writer are recovered (see below)
    2. the destination is checked: absent, or (overwrite) a directory ``replaceable`` accepts
    3. the caller writes into the temporary directory
    4. absent destination: rename(tmp, dest)
       existing one:       rename(dest, .<name>.imitrl-old-<hex>); rename(tmp, dest);
                           remove the old one (if the second rename fails, the first is undone)

A second writer of the same path fails at once with a ValueError naming the holder,
and so does any writer of a path that exists (without ``overwrite``): of two writers,
at most one succeeds. Leftovers of a killed writer are handled by the next call, under
the lock: a temporary directory is an unfinished write and is removed; an ``old``
directory beside a missing destination is the previous dataset, caught between the
two renames, and is moved back; beside a present destination it is what a finished
swap had not yet removed, and is removed. Each is named in a warning.

The working directory, or any directory holding it, is never replaced.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

try:
    import fcntl
except ImportError:  # not POSIX: an O_EXCL lock file (a killed writer's must be removed by hand)
    fcntl = None

__all__ = ["publishing"]

LOCK = ".imitrl-lock"
TMP = ".imitrl-tmp-"
OLD = ".imitrl-old-"


def _absolute(path: str | Path) -> Path:
    """``path`` made absolute, ``..`` folded (symlinks are not followed: a link is refused
    at the destination check, not replaced)."""
    target = Path(os.path.abspath(path))
    if target.name in ("", ".", ".."):
        raise ValueError(f"{path!r} names no directory that can be written (resolved: {target})")
    return target


def _refuse_working_directory(target: Path, given: str | Path) -> None:
    cwd = Path.cwd().resolve()
    resolved = target.resolve()
    if resolved == cwd or resolved in cwd.parents:
        raise ValueError(
            f"{given!r} is the working directory or holds it ({resolved}); a dataset is never "
            "written over it: choose a new directory"
        )


@contextmanager
def _locked(target: Path) -> Iterator[None]:
    """Hold ``.<name>.imitrl-lock`` beside ``target``; ValueError if another process holds it."""
    lock = target.parent / f".{target.name}{LOCK}"
    if fcntl is None:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise ValueError(
                f"{target} is being written by another process ({lock} exists; if no write is "
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
                    f"{target} is being written by another process ({holder}, holding {lock}); "
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
    try:
        yield
    finally:
        try:
            os.unlink(lock)  # while still holding it (see the retry above)
        except FileNotFoundError:
            pass
        os.close(fd)


def _leftovers(target: Path, mark: str) -> list[Path]:
    pattern = re.compile(re.escape(f".{target.name}{mark}") + r"[A-Za-z0-9_]+")
    return sorted(p for p in target.parent.iterdir() if pattern.fullmatch(p.name))


def _recover(target: Path) -> None:
    """Finish or undo what a killed writer of ``target`` left (the lock is held)."""
    done: list[str] = []
    for tmp in _leftovers(target, TMP):
        shutil.rmtree(tmp)
        done.append(f"removed {tmp.name} (an unfinished write)")
    olds = _leftovers(target, OLD)
    if olds and not os.path.lexists(target):
        if len(olds) > 1:
            raise ValueError(
                f"{target} is missing and several earlier versions lie beside it "
                f"({[p.name for p in olds]}); move the right one back to {target.name} by hand"
            )
        os.rename(olds[0], target)
        done.append(f"moved {olds[0].name} back to {target.name} (a replacement cut short)")
    else:
        for old in olds:
            shutil.rmtree(old)
            done.append(f"removed {old.name} (replaced by a finished write)")
    if done:
        warnings.warn(
            f"{target.parent}: a killed writer's leftovers: " + "; ".join(done),
            UserWarning,
            stacklevel=5,  # the caller of save_lerobot
        )


def _check_destination(
    target: Path, given: str | Path, overwrite: bool, replaceable: Callable[[Path], None]
) -> None:
    if not os.path.lexists(target):
        return
    if not overwrite:
        raise ValueError(f"{given} exists; pass overwrite=True to replace it")
    if target.is_symlink() or not target.is_dir():
        kind = "a symbolic link" if target.is_symlink() else "not a directory"
        raise ValueError(f"{given} is {kind}; overwrite=True replaces only a dataset directory")
    replaceable(target)


def _swap_in(tmp: Path, target: Path) -> None:
    """``tmp`` becomes ``target``; an existing ``target`` is moved aside first and removed
    after, or moved back if the rename fails."""
    if not os.path.lexists(target):
        os.rename(tmp, target)  # atomic; fails (ENOTEMPTY) rather than merge into a new dir
        return
    old = target.parent / f".{target.name}{OLD}{secrets.token_hex(6)}"
    os.rename(target, old)
    try:
        os.rename(tmp, target)
    except BaseException:
        os.rename(old, target)
        raise
    shutil.rmtree(old)


@contextmanager
def publishing(
    path: str | Path, *, overwrite: bool, replaceable: Callable[[Path], None]
) -> Iterator[Path]:
    """A fresh directory to write into; it becomes ``path`` when the block ends without
    error, atomically and under an exclusive lock (see the module docstring).

    Args:
        path: the destination directory (its parents are created).
        overwrite: replace an existing ``path``, which ``replaceable`` must accept.
        replaceable: raises ValueError (saying why) unless the directory may be replaced.

    Raises:
        ValueError: ``path`` is (or holds) the working directory; exists and not
            ``overwrite``; is not a directory ``replaceable`` accepts; another process is
            writing it; a killed writer left something that cannot be sorted out safely.
    """
    target = _absolute(path)
    _refuse_working_directory(target, path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with _locked(target):
        _recover(target)
        _check_destination(target, path, overwrite, replaceable)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}{TMP}", dir=target.parent))
        try:
            yield tmp
            _check_destination(target, path, overwrite, replaceable)  # other programs
            _swap_in(tmp, target)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
