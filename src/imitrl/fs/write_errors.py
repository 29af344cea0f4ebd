"""A write the file system refuses, named as such: a full disk, or a folder imitrl may
not write (read-only, or another user's).

A full disk:

The libraries underneath report a full file system each in their own way: ``OSError``
with ``errno`` 28 (``ENOSPC``) or 122 (``EDQUOT``) and no file name from ``os.write``
and numpy, an ``OSError`` whose text says "No space left on device" from pyarrow, a
``RuntimeError`` about a failed write from ``torch.save``. :func:`reporting_disk_full`
turns each into one :class:`DiskFullError` (an ``OSError``, ``errno`` ``ENOSPC``) that
names the destination, the free space on its file system, and what the writer left:
the writers of this library stage their files beside the destination and publish them
only when complete (:mod:`imitrl.fs.publish`), so a full disk leaves the previous
contents whole.

A folder that cannot be written (``EACCES``, ``EPERM`` or ``EROFS`` from any of them)
becomes one :class:`NotWritableError` (an ``OSError``) naming the destination and the
folder refused, so the command line prints one line instead of a traceback.
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["DiskFullError", "NotWritableError", "is_disk_full", "reporting_disk_full"]

_CODES = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}
_TEXTS = ("no space left on device", "disk quota exceeded", "[errno 28]", "errno 28")


class DiskFullError(OSError):
    """The file system of ``filename`` filled up while this library wrote to it."""

    def __init__(self, path: Path, what: str, left: str) -> None:
        free = _free(path)
        message = (
            f"no space left on the device while writing {what} to {path} ({free}); {left}. "
            "Free some space or choose a destination on another disk, then run it again"
        )
        super().__init__(errno.ENOSPC, message)
        self.filename = str(path)

    def __str__(self) -> str:
        return f"[Errno {self.errno}] {self.strerror}"


class NotWritableError(OSError):
    """The file system refused a write: a read-only folder, or one this user may not write."""

    def __init__(self, path: Path, what: str, err: OSError) -> None:
        refused = err.filename or path
        message = (
            f"cannot write {what} to {path}: {refused} is {_why(err)}; nothing was written "
            "there. Choose a folder you can write, or change its permissions"
        )
        super().__init__(err.errno, message)
        self.filename = str(path)

    def __str__(self) -> str:
        return str(self.strerror)


_REFUSED = {errno.EACCES, errno.EPERM, errno.EROFS}


def _why(err: OSError) -> str:
    if err.errno == errno.EROFS:
        return "on a read-only file system"
    return "not writable by this user (permission denied)"


def not_writable(err: BaseException) -> OSError | None:
    """The permission error ``err`` was raised from (itself included), if any."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno in _REFUSED:
            return current
        current = current.__cause__ or current.__context__
    return None


def is_disk_full(err: BaseException) -> bool:
    """Whether ``err`` (or an exception it was raised from) reports a full file system."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno in _CODES:
            return True
        text = str(current).lower()
        if isinstance(current, OSError | RuntimeError) and any(t in text for t in _TEXTS):
            return True
        current = current.__cause__ or current.__context__
    return False


def _free(path: Path) -> str:
    probe = Path(path)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        return f"{shutil.disk_usage(probe).free / 2**20:.1f} MiB free on its file system"
    except OSError:
        return "free space unknown"


@contextmanager
def reporting_disk_full(
    path: str | Path, *, what: str, left: str = "nothing was published: it is as it was"
) -> Iterator[None]:
    """Run the block; a full file system inside it becomes a :class:`DiskFullError`
    naming ``path`` (the destination), ``what`` was written and what is ``left``, and a
    refused write a :class:`NotWritableError`."""
    try:
        yield
    except (DiskFullError, NotWritableError):
        raise
    except (OSError, RuntimeError) as err:
        if is_disk_full(err):
            raise DiskFullError(Path(os.path.abspath(path)), what, left) from err
        refused = not_writable(err)
        if refused is None:
            raise
        raise NotWritableError(Path(os.path.abspath(path)), what, refused) from err
