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

Resume trusts nothing the directory holds (it may have been copied from elsewhere, or
edited): ``imitrl_buffer.json`` is read by descriptor, a regular file of at most
:data:`LAYOUT_LIMIT` bytes (no link, no FIFO); each column's ``file`` must be
``storage/`` followed by plain names (a nested key's folders, then the file: no absolute
path, no ``..``); every file is opened one name at a time without following a link
(:func:`open_column`), must be a regular file of one name (not a hard link to a file
elsewhere), and is mapped through its descriptor (``/proc/self/fd/N``), so the file
mapped is the file checked. ``rows`` and ``capacity`` must fit in the bytes each file
holds (a file of N bytes holds N // row_bytes rows): resuming never lengthens a file.
Growth and the regular remaps open the files the same way.
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
from imitrl.data.validation import STORED_DTYPES
from imitrl.fs.contained import plain_name
from imitrl.fs.files import (
    PlantedLinkError,
    check_regular,
    make_folder,
    open_own,
    remove_tree,
    replace_file,
)
from imitrl.fs.reading import OpenedFolder, fd_path, parse_json
from imitrl.fs.write_errors import DiskFullError, is_disk_full, reporting_disk_full

__all__ = [
    "LAYOUT",
    "LAYOUT_LIMIT",
    "DiskLayout",
    "GrowingMemmapStorage",
    "check_columns",
    "drop_uncommitted",
    "open_column",
]

LAYOUT = "imitrl_buffer.json"
LOCK = "imitrl_buffer.lock"
STORAGE = "storage"
FORMAT = "imitrl.DiskBuffer/1"
REMAP_BYTES = 64 << 20
"""written bytes after which the files are mapped again (bounds this process's RssFile)"""
FAULT_AROUND_BYTES = 64 << 10
"""what one page fault may map of a file in the page cache (Linux ``fault_around_bytes``)"""
LAYOUT_LIMIT = 16 << 20
"""bytes ``imitrl_buffer.json`` may hold on resume (a buffer of a few dozen keys writes a
few kB); a larger file is refused before it is read"""
MAX_COUNT = 2**63 - 1
"""the largest ``rows``, ``capacity`` or episode id a layout may name (int64)"""

_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_FOLDER = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | _CLOEXEC
_COLUMN = os.O_RDWR | os.O_NOFOLLOW | os.O_NONBLOCK | _CLOEXEC

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
        root = Path(self.scratch_dir).parent
        for column in self.columns(root):
            row = _row_bytes(column)
            fd = open_column(root, column["file"])
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
        (entries of :meth:`columns`, relative to the buffer's directory, checked by
        :func:`check_columns`) and ``rows``: open the files a previous process wrote
        (resume); a file too short for the ``rows`` or the ``capacity`` it should hold
        is refused (resuming never lengthens a file). Every file is opened by
        :func:`open_column` and mapped through that descriptor.
        """
        root = Path(self.scratch_dir).parent
        resume = columns is not None
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
            row = _row_bytes(column)
            fd = open_column(root, column["file"])
            try:
                size = os.fstat(fd).st_size
                if size < rows * row:
                    raise ValueError(f"{filename}: {size} bytes, {rows} rows need {rows * row}")
                if resume and size < capacity * row:
                    raise ValueError(
                        f"{filename}: {size} bytes, a capacity of {capacity} rows needs "
                        f"{capacity * row}; a disk buffer's files hold their capacity"
                    )
                if size < capacity * row:  # sparse: no disk used until written
                    os.ftruncate(fd, capacity * row)
                tensor = _map_descriptor(fd, filename, dtype, torch.Size([capacity, *shape]))
            finally:
                os.close(fd)
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


def _map_descriptor(
    fd: int, filename: Path, dtype: torch.dtype, shape: torch.Size
) -> MemoryMappedTensor:
    """The file open at ``fd`` mapped read-write (shared) as a tensor of ``shape``, its
    ``filename`` the name it is recorded under (``columns``, pickling).

    What ``MemoryMappedTensor.from_filename(filename, dtype, shape)`` does (tensordict
    0.14.3: ``torch.from_file``, then the same attributes), except that the file mapped
    is opened through ``/proc/self/fd/<fd>``: the very file :func:`open_column` checked,
    whatever ``filename`` names by now. ``from_filename`` itself records the path it
    opened, which names the descriptor, closed once mapped."""
    flat = torch.from_file(
        fd_path(fd), shared=True, dtype=dtype, size=shape.numel(), device=torch.device("cpu")
    )
    tensor = MemoryMappedTensor(flat.view(shape))
    tensor.filename = str(filename)
    tensor.index, tensor.parent_shape = None, shape
    return tensor


def _row_bytes(column: dict[str, Any]) -> int:
    """Bytes one row of ``column`` takes in its file."""
    dtype = getattr(torch, column["dtype"])
    return torch.Size(column["shape"]).numel() * torch.empty((), dtype=dtype).element_size()


def open_column(root: Path, file: str) -> int:
    """A read-write descriptor of the column file ``root/file`` (``file``: ``storage/``
    then plain names, see :func:`check_columns`), opened one name at a time without
    following a link (``O_NOFOLLOW``; a FIFO never blocks the open) and checked to be a
    regular file of one name (:func:`imitrl.fs.files.check_regular`). The caller closes it.

    Raises:
        PlantedLinkError: a link, a FIFO, a device, a folder or a hard link at a name.
        ValueError: the file is missing.
    """
    path = root / file
    parts = file.split("/")
    what = "a disk buffer's column file"
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY | _CLOEXEC)  # the directory given
    try:
        for name in parts[:-1]:
            folder = os.open(name, _FOLDER, dir_fd=fd)
            os.close(fd)
            fd = folder
        column = os.open(parts[-1], _COLUMN, dir_fd=fd)
    except OSError as err:
        if err.errno in (errno.ELOOP, errno.ENOTDIR):  # a link (or a file) at a folder's name
            raise PlantedLinkError(
                f"{path}: a symbolic link or another file stands on the way to {what}; "
                "a disk buffer holds its own regular files only"
            ) from None
        if err.errno == errno.ENOENT:
            raise ValueError(f"{path}: missing ({what})") from None
        raise
    finally:
        os.close(fd)
    check_regular(column, path, what)
    return column


def check_columns(columns: Any, *, where: str) -> list[dict[str, Any]]:
    """``columns`` as a layout may hold them: a list of ``{"key": [str, ...], "dtype":
    a torch dtype's name, "shape": [int >= 0, ...], "file": "storage/<name>[/<name>...]"}``,
    keys and files distinct, the files inside ``storage/`` (plain names, no ``..``)."""
    if not isinstance(columns, list):
        raise ValueError("columns must be a list")
    files, keys = set(), set()
    for column in columns:
        if not isinstance(column, dict) or set(column) != {"key", "dtype", "shape", "file"}:
            raise ValueError(f"a column must hold key, dtype, shape and file, got {column!r}")
        key, shape, file = column["key"], column["shape"], column["file"]
        if not isinstance(key, list) or not key or not all(isinstance(k, str) for k in key):
            raise ValueError(f"a column's key must be a list of strings, got {key!r}")
        dtype = column["dtype"]
        if not isinstance(dtype, str) or getattr(torch, dtype, None) not in STORED_DTYPES:
            raise ValueError(f"{dtype!r} is not a dtype a buffer stores")
        if not isinstance(shape, list) or not all(type(d) is int and d >= 0 for d in shape):
            raise ValueError(f"a column's shape must be a list of integers >= 0, got {shape!r}")
        parts = file.split("/") if isinstance(file, str) else []
        if len(parts) < 2 or parts[0] != STORAGE:
            raise ValueError(f"a column's file must lie in {STORAGE}/ of the buffer, got {file!r}")
        for part in parts[1:]:
            plain_name(part, what=f"the column file {file!r}'s part", where=where)
        if tuple(key) in keys or file in files:
            raise ValueError(f"two columns name the key {key!r} or the file {file!r}")
        keys.add(tuple(key))
        files.add(file)
    return columns


def drop_uncommitted(scratch_dir: Path) -> None:
    """Remove the column files of a buffer whose layout records none: a first write
    killed before its commit created them (TorchRL creates them at the first write, and
    refuses existing ones), so they hold no committed row."""
    if os.path.lexists(scratch_dir):
        remove_tree(scratch_dir)


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
            only_lock = (
                " (only the lock of one that stopped before it stored anything: "
                "start it afresh, without resume)"
                if entries == [LOCK]
                else ""
            )
            raise ValueError(
                f"cannot resume: {self.path} holds no disk buffer (no {LAYOUT}){only_lock}"
            )
        others = [e for e in entries if e != LOCK]  # a lock alone: a buffer that never wrote
        if not resume and others:
            what = "a disk buffer" if LAYOUT in entries else f"other files ({others[:3]})"
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
        """The layout a previous buffer wrote, checked (module docstring: the files it
        names are checked when they are opened, :meth:`GrowingMemmapStorage.map`)."""
        where = self.path / LAYOUT
        try:  # by descriptor: no link followed, a FIFO never waited on, the size bounded
            with OpenedFolder(self.path, what="disk buffer", links=False) as folder:
                data = folder.read_bytes(LAYOUT, named_by=LAYOUT, limit=LAYOUT_LIMIT)
            stored = parse_json(data, where=str(where))
            if stored["format"] != FORMAT:
                raise ValueError(f"format {stored['format']!r}, expected {FORMAT!r}")
            for name in ("rows", "capacity", "next_episode", "num_episodes"):
                if type(stored[name]) is not int or not 0 <= stored[name] <= MAX_COUNT:
                    raise ValueError(f"{name} must be an integer in [0, {MAX_COUNT}]")
            if stored["rows"] > stored["capacity"]:
                raise ValueError("more rows than capacity")
            if stored["num_episodes"] > stored["rows"]:  # an episode has a row at least
                raise ValueError(f"{stored['num_episodes']} episodes in {stored['rows']} rows")
            states = stored["num_states"]
            if not (states is None or (type(states) is int and 1 <= states <= MAX_COUNT)):
                raise ValueError(f"num_states must be null or an integer >= 1, got {states!r}")
            stored["columns"] = check_columns(stored["columns"], where=str(where))
            if (stored["rows"] or stored["columns"]) and not any(
                _row_bytes(c) for c in stored["columns"]
            ):  # rows and capacity are bounded by the bytes of the files that hold them
                raise ValueError(f"{stored['rows']} rows, but no column file holds them")
            stored["schema"] = _schema_from_json(stored["schema"])
        except (OSError, KeyError, TypeError, ValueError, AttributeError) as err:
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
