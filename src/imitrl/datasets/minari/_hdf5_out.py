"""The HDF5 file :func:`~imitrl.datasets.minari.save_minari` writes, meeting a full disk
with an ``OSError`` (``ENOSPC``), never a crash.

Why not let HDF5 write the file itself: when one of its writes fails (a full disk:
``ENOSPC``), HDF5 raises, keeps the unwritten metadata dirty, and closing the file tries
to flush it again; the close fails, leaves an identifier h5py can neither use nor
release, and the process ends with SIGSEGV (exit 139, every time on a 256 KiB tmpfs,
h5py 3.16 / HDF5 2.0: h5py issue #914, open since 2017). Checking the free space first
(``statvfs``) or preallocating (``posix_fallocate``) would need the file's exact size
before it is written, and another writer may take the space between the check and the
write; building the whole file in memory (the ``core`` driver) would hold a copy of the
dataset, which may be larger than memory (a disk-backed buffer).

So HDF5 writes through h5py's file-object driver into :class:`_Spilling`, which writes
to the real file with ``os.pwrite`` and never lets HDF5 see a failed write: the first
``OSError`` is kept, and from then on every write (and every read of what was written)
goes to memory instead. HDF5 sees a file that works, so the close succeeds; the writer
raises the kept error after the episode that met it (:meth:`HDF5Out.check`), so what
went to memory is at most one episode and the file's last metadata. The file holds what
HDF5's own driver writes (laid out a little differently: 0.1% smaller; ``minari``'s own
reader reads it, ``tests/datasets/minari/test_write.py``), 10 to 20% slower to write, since each
read and write crosses into Python (300 episodes, 13 MB: 0.41 s against 0.37 s).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

__all__ = ["HDF5Out"]

_CREATE = os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
"""a new file, never through a link, open for reading too: HDF5 reads back what it wrote
(its metadata cache evicts entries and loads them again on a file of a few thousand
episodes)"""


class _Spilling:
    """A file object over ``fd`` for h5py's ``fileobj`` driver (module docstring): the
    first failed write is kept in :attr:`failed`, and what follows is held in memory."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.pos = 0
        self.size = 0
        self.failed: OSError | None = None
        self.spilled: list[tuple[int, bytes]] = []
        """``(offset, bytes)`` written after the failure, in order (later ones win)"""

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self.pos, os.SEEK_END: self.size}[whence]
        self.pos = base + offset
        return self.pos

    def tell(self) -> int:
        return self.pos

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        if self.failed is None:
            try:
                done = 0
                while done < len(view):
                    done += os.pwrite(self.fd, view[done:], self.pos + done)
            except OSError as err:
                self.failed = err
        if self.failed is not None:
            self.spilled.append((self.pos, bytes(view)))
        self.pos += len(view)
        self.size = max(self.size, self.pos)
        return len(view)

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        n = max(0, min(len(view), self.size - self.pos))
        got = os.preadv(self.fd, [view[:n]], self.pos) if n else 0
        view[got:n] = bytes(n - got)  # past what reached the disk
        for offset, piece in self.spilled:
            lo, hi = max(offset, self.pos), min(offset + len(piece), self.pos + n)
            if lo < hi:
                view[lo - self.pos : hi - self.pos] = piece[lo - offset : hi - offset]
        self.pos += n
        return n

    def read(self, n: int = -1) -> bytes:
        buffer = bytearray(max(0, self.size - self.pos) if n < 0 else n)
        return bytes(buffer[: self.readinto(buffer)])

    def truncate(self, size: int | None = None) -> int:
        size = self.pos if size is None else size
        if self.failed is None:
            try:
                os.ftruncate(self.fd, size)
            except OSError as err:
                self.failed = err
        self.size = size
        return size

    def flush(self) -> None:
        """Nothing buffered here: every write went to the file (or to memory)."""


class HDF5Out:
    """A new HDF5 file at ``path`` (created ``O_EXCL | O_NOFOLLOW``), open for writing as
    ``with HDF5Out(path) as h5:``; a full disk (or any failed write) is raised as its
    ``OSError`` by :meth:`check` and on leaving the block, after HDF5 closed the file
    cleanly. The file is fsynced on a clean exit."""

    def __init__(self, path: Path, **kwargs: Any) -> None:
        self.path = path
        self.kwargs = kwargs
        self._file: _Spilling | None = None
        self._h5: Any = None

    def __enter__(self) -> Any:
        import h5py

        fd = os.open(self.path, _CREATE, 0o666)  # in a staging folder of its own
        self._file = _Spilling(fd)
        try:
            self._h5 = h5py.File(self._file, "w", **self.kwargs)
        except BaseException:
            os.close(fd)
            raise
        return self._h5

    def check(self) -> None:
        """Raise the first failed write's ``OSError`` (``ENOSPC`` for a full disk), if any."""
        if self._file is not None and self._file.failed is not None:
            raise self._file.failed

    def __exit__(self, kind: type | None, *exc: object) -> None:
        assert self._file is not None  # __enter__ returned: it opened the file
        try:
            self._h5.close()  # never fails on a write: they all succeed, to disk or memory
            if kind is None:
                self.check()
                os.fsync(self._file.fd)
        finally:
            os.close(self._file.fd)
