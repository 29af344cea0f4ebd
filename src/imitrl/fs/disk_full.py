"""A full disk named as such: which path was being written, and what is left there.

The libraries underneath report a full file system each in their own way: ``OSError``
with ``errno`` 28 (``ENOSPC``) or 122 (``EDQUOT``) and no file name from ``os.write``
and numpy, an ``OSError`` whose text says "No space left on device" from pyarrow, a
``RuntimeError`` about a failed write from ``torch.save``. :func:`reporting_disk_full`
turns each into one :class:`DiskFullError` (an ``OSError``, ``errno`` ``ENOSPC``) that
names the destination, the free space on its file system, and what the writer left:
the writers of this library stage their files beside the destination and publish them
only when complete (:mod:`imitrl.fs.publish`), so a full disk leaves the previous
contents whole.
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["DiskFullError", "is_disk_full", "reporting_disk_full"]

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


def is_disk_full(err: BaseException) -> bool:
    """Whether ``err`` (or an exception it was raised from) reports a full file system."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, OSError) and err.errno in _CODES:
            return True
        text = str(err).lower()
        if isinstance(err, OSError | RuntimeError) and any(t in text for t in _TEXTS):
            return True
        err = err.__cause__ or err.__context__
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
    naming ``path`` (the destination), ``what`` was written and what is ``left``."""
    try:
        yield
    except DiskFullError:
        raise
    except (OSError, RuntimeError) as err:
        if not is_disk_full(err):
            raise
        raise DiskFullError(Path(os.path.abspath(path)), what, left) from err
