"""A demonstration buffer's rows on disk: memory-mapped files that grow, never wrap.

``DemonstrationBuffer(path=...)`` keeps its rows in TorchRL's ``LazyMemmapStorage``
(scratch directory ``path/storage``), one file per key, mapped into memory: the rows
live in the page cache, which the kernel evicts as it needs, not in the process's own
memory. Layout of ``path``::

    path/
      imitrl_buffer.json   format, rows, capacity, next_episode, num_episodes,
                           num_states, schema, and every column (key, dtype, trailing
                           shape, file); rewritten (atomically) after every extend
      imitrl_buffer.lock   held (flock) by the one buffer object using the directory
      storage/...          TorchRL's memory-mapped files, ``capacity`` rows each

Growth (:meth:`GrowingMemmapStorage.reserve`): when the rows would not fit, every file
is lengthened in place (``os.truncate``; the new tail is sparse, so capacity costs no
disk) and mapped again at the new size, doubling the capacity: no row is copied, so a
growth costs the same at 1e3 rows as at 1e8 (measured in ``benchmarks/scale_buffer.py``;
allocating a bigger memmap and copying would write every row again at each doubling).
The mapping is also renewed after every ``REMAP_BYTES`` written, so pages this process
wrote leave its resident set (they stay in the page cache, written back by the kernel).

Crash safety: rows are written into the files first and counted in
``imitrl_buffer.json`` after, so a process killed mid-extend leaves the previous rows
and count; the rows past the count are ignored on resume. Nothing is fsynced: the files
survive the process, not a power cut.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
from pathlib import Path
from typing import Any

import torch
from tensordict import MemoryMappedTensor, TensorDict
from torchrl.data.replay_buffers import LazyMemmapStorage

from imitrl.compat import replace_storage_contents
from imitrl.fs.files import make_folder, open_own, replace_file
from imitrl.fs.write_errors import DiskFullError, is_disk_full, reporting_disk_full

__all__ = ["LAYOUT", "DiskLayout", "GrowingMemmapStorage"]

LAYOUT = "imitrl_buffer.json"
LOCK = "imitrl_buffer.lock"
STORAGE = "storage"
FORMAT = "imitrl.DiskBuffer/1"
REMAP_BYTES = 64 << 20
"""written bytes after which the files are mapped again (bounds this process's RssFile)"""
FAULT_AROUND_BYTES = 64 << 10
"""what one page fault may map of a file in the page cache (Linux ``fault_around_bytes``)"""

Schema = dict[str, tuple[str, tuple[int, ...]]]


_MADV_PAGEOUT = 21  # Linux >= 5.4: reclaim the range's pages; contents are kept
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def release_pages(rows: TensorDict) -> None:
    """Let the kernel reclaim the pages of ``rows``' memory-mapped leaves from this
    process (``madvise(MADV_PAGEOUT)``: a hint that never changes a value; clean file
    pages are dropped and re-read on the next access). An extend that copies a
    memory-mapped source (frames decoded into a file, say) slice by slice calls it on
    each slice read, so the source does not stay resident. The range is widened by
    :data:`FAULT_AROUND_BYTES` on each side (within the mapped file): reading a slice's
    first pages also maps the cached pages just before it, which a pass slice after
    slice would otherwise leave mapped, tens of kB per slice and column. No-op where
    unsupported."""
    libc = _libc()
    if libc is None:
        return
    for leaf in rows.values(include_nested=True, leaves_only=True):
        if not isinstance(leaf, MemoryMappedTensor) or not leaf.is_contiguous():
            continue
        storage = leaf.untyped_storage()
        lowest, highest = storage.data_ptr(), storage.data_ptr() + storage.nbytes()
        start = max(lowest, leaf.data_ptr() - FAULT_AROUND_BYTES) // _PAGE * _PAGE
        end = leaf.data_ptr() + leaf.numel() * leaf.element_size()
        end = min(highest, end + FAULT_AROUND_BYTES)
        if end > start:
            libc.madvise(ctypes.c_void_p(start), ctypes.c_size_t(end - start), _MADV_PAGEOUT)


def _libc():
    try:
        return ctypes.CDLL(None, use_errno=True) if os.name == "posix" else None
    except OSError:
        return None


class GrowingMemmapStorage(LazyMemmapStorage):
    """A ``LazyMemmapStorage`` in ``scratch_dir`` that grows its files instead of wrapping.

    Call :meth:`reserve` before writing ``n`` rows (``DemonstrationBuffer.extend`` does).
    """

    def __init__(self, scratch_dir: Path, capacity: int) -> None:
        super().__init__(int(capacity), scratch_dir=scratch_dir, existsok=False, auto_cleanup=False)
        self._unmapped_rows = 0  # rows written since the files were last mapped
        self._read_bytes = 0  # what random reads may have mapped since then
        self._pending = 0  # rows the next write brings (their disk space is allocated first)

    def reserve(self, n: int) -> bool:
        """Make room for ``n`` more rows, their disk space allocated (:meth:`allocate`);
        returns True if the storage grew."""
        need = len(self) + int(n)
        grew = need > self.max_size
        if grew:
            self.map(max(2 * self.max_size, need))
        elif self.initialized and self._unmapped_rows * self.row_bytes() > REMAP_BYTES:
            self.map(self.max_size)
        self._unmapped_rows += 0 if grew else int(n)
        self._pending = int(n)
        if self.initialized:
            self.allocate(len(self), self._pending)
        return grew

    def _init(self, data) -> None:
        # LazyMemmapStorage creates its files at the first write, then writes through
        # the mapping at once: the rows' disk space is allocated in between, so that a
        # full disk is an error here instead of a SIGBUS at the write (torchrl 0.14.1's
        # private hook; the files are TorchRL's, created sparse)
        super()._init(data)
        self.allocate(0, self._pending)

    def allocate(self, first: int, n: int) -> None:
        """Allocate the disk blocks of rows ``[first, first + n)`` in every file
        (``posix_fallocate``): a row written through the mapping into a sparse file on a
        full disk would kill the process with SIGBUS, where this raises
        :class:`imitrl.fs.DiskFullError` naming the buffer, its rows untouched."""
        if n <= 0 or not hasattr(os, "posix_fallocate"):
            return
        for tensor in self._storage.values(True, True):
            row = tensor[0].nbytes
            fd = os.open(tensor.filename, os.O_RDWR)
            try:
                os.posix_fallocate(fd, first * row, n * row)
            except OSError as err:
                if not is_disk_full(err):
                    if err.errno in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                        return  # a file system without it: writes fail as they would
                    raise
                where = Path(self.scratch_dir).parent
                raise DiskFullError(
                    where, f"{n} rows of a disk buffer", f"the buffer keeps its {first} rows"
                ) from err
            finally:
                os.close(fd)

    def note_reads(self, n: int) -> None:
        """Count ``n`` randomly read rows; map the files again once they may have mapped
        ``REMAP_BYTES`` (each read of a row maps up to ``FAULT_AROUND_BYTES`` per column:
        the kernel maps the cached neighbours of a faulting page too)."""
        # a column's reads map at most its whole file
        files = [t.nbytes for t in self._storage.values(True, True)]
        self.note_bytes(sum(min(n * FAULT_AROUND_BYTES, size) for size in files))

    def note_bytes(self, nbytes: int) -> bool:
        """Count ``nbytes`` read through the mapping; map the files again (returns True)
        once ``REMAP_BYTES`` may be mapped: views taken before then keep the old mapping
        (and its pages) alive, so readers take new views after a remap."""
        # what is mapped never exceeds the files themselves: files of REMAP_BYTES or
        # less in all are never mapped again for reads
        files = sum(t.nbytes for t in self._storage.values(True, True)) if self.initialized else 0
        self._read_bytes = min(self._read_bytes + int(nbytes), files)
        if self._read_bytes > REMAP_BYTES:
            self.map(self.max_size)
            return True
        return False

    def row_bytes(self) -> int:
        return sum(t[0].nbytes for t in self._storage.values(True, True)) if self.initialized else 0

    def map(
        self, capacity: int, columns: list[dict[str, Any]] | None = None, rows: int = -1
    ) -> None:
        """(Re)map every file at ``capacity`` rows, lengthening files that are shorter.

        Without ``columns``: the storage's own files, keeping its rows. With ``columns``
        (entries of :meth:`columns`, relative to the buffer's directory) and ``rows``:
        open the files a previous process wrote (resume); a file too short for the
        ``rows`` it should hold is refused.
        """
        root = Path(self.scratch_dir).parent
        if columns is None:
            if not self.initialized:
                self.max_size = int(capacity)
                return
            columns, rows = self.columns(root), len(self)
        contents = TensorDict({}, batch_size=[capacity])
        for column in columns:
            shape = torch.Size(column["shape"])
            dtype = getattr(torch, column["dtype"])
            filename = root / column["file"]
            row = shape.numel() * torch.empty((), dtype=dtype).element_size()
            size = filename.stat().st_size
            if size < rows * row:
                raise ValueError(f"{filename}: {size} bytes, {rows} rows need {rows * row}")
            if size < capacity * row:
                os.truncate(filename, capacity * row)  # sparse: no disk used until written
            tensor = MemoryMappedTensor.from_filename(filename, dtype, (capacity, *shape))
            parts = column["key"]
            contents.set(tuple(parts) if len(parts) > 1 else parts[0], tensor)
        replace_storage_contents(self, contents, rows)
        self._unmapped_rows = self._read_bytes = 0

    def columns(self, root: Path) -> list[dict[str, Any]]:
        """Every key's ``{"key": [parts], "dtype", "shape", "file"}`` (file relative to ``root``)."""
        if not self.initialized:
            return []
        out = []
        for key, tensor in self._storage.items(include_nested=True, leaves_only=True):
            out.append(
                {
                    "key": [key] if isinstance(key, str) else list(key),
                    "dtype": str(tensor.dtype).removeprefix("torch."),
                    "shape": list(tensor.shape[1:]),
                    "file": os.path.relpath(tensor.filename, root),
                }
            )
        return out


class DiskLayout:
    """The directory of a disk buffer: refuses an occupied one, holds its lock, writes
    ``imitrl_buffer.json``.

    Args:
        path: the buffer's directory: absent or empty for a new buffer; with ``resume``
            one a disk buffer wrote.
        resume: continue the buffer stored at ``path`` (its rows, schema, episode ids).
    """

    def __init__(self, path: str | Path, *, resume: bool) -> None:
        self.path = Path(path).expanduser().absolute()
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"{self.path} is not a directory: a disk buffer needs a directory")
        entries = sorted(os.listdir(self.path)) if self.path.is_dir() else []
        if resume and LAYOUT not in entries:
            raise ValueError(f"cannot resume: {self.path} holds no disk buffer (no {LAYOUT})")
        if not resume and entries:
            what = "a disk buffer" if LAYOUT in entries else f"other files ({entries[:3]})"
            raise ValueError(
                f"{self.path} already holds {what}: refusing to overwrite it; pass "
                "resume=True to continue a disk buffer there, or choose an empty directory"
            )
        make_folder(self.path)
        # opened without following a link planted at its name (imitrl.fs.files)
        self._lock = os.fdopen(open_own(self.path / LOCK, what="a disk buffer's lock"), "a")
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock.close()
            raise ValueError(f"{self.path} is in use by another disk buffer") from None
        self.stored = self._read() if resume else None

    def close(self) -> None:
        """Release the directory's lock (another buffer may then resume it)."""
        self._lock.close()

    @property
    def scratch_dir(self) -> Path:
        return self.path / STORAGE

    def _read(self) -> dict[str, Any]:
        where = self.path / LAYOUT
        try:
            stored = json.loads(where.read_text())
            if stored["format"] != FORMAT:
                raise ValueError(f"format {stored['format']!r}, expected {FORMAT!r}")
            for name in ("rows", "capacity", "next_episode", "num_episodes"):
                if type(stored[name]) is not int or stored[name] < 0:
                    raise ValueError(f"{name} must be a non-negative integer")
            if stored["rows"] > stored["capacity"]:
                raise ValueError("more rows than capacity")
            stored["schema"] = _schema_from_json(stored["schema"])
        except (OSError, KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{where}: not a readable disk buffer layout ({err})") from None
        return stored

    def write(self, content: dict[str, Any]) -> None:
        """Replace ``imitrl_buffer.json`` atomically (a crash leaves the old or the new)."""
        body = {"format": FORMAT, **content}
        if body["schema"] is not None:
            body["schema"] = {k: [d, list(s)] for k, (d, s) in body["schema"].items()}
        left = f"{LAYOUT} keeps the previous count of rows"
        with reporting_disk_full(self.path, what=f"a disk buffer's {LAYOUT}", left=left):
            text = json.dumps(body, indent=1, sort_keys=True) + "\n"
            replace_file(self.path / LAYOUT, text, what=LAYOUT, durable=False)  # never via a link


def _schema_from_json(schema: Any) -> Schema | None:
    if schema is None:
        return None
    return {k: (str(d), tuple(int(s) for s in shape)) for k, (d, shape) in schema.items()}
