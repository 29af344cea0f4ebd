"""Which files of a folder any process opened, read or changed: Linux inotify via ctypes.

The hostile-input tests put decoys (a real parquet file, an mp4, a folder) outside the
dataset under test, watch them, load the dataset, and assert that nothing outside was
opened, read, written or created. inotify sees every access by any code in the process
(pyarrow, PyAV, h5py read files from C, where Python's audit hooks see nothing).
"""

from __future__ import annotations

import ctypes
import os
import struct
from pathlib import Path

IN_ACCESS, IN_MODIFY, IN_ATTRIB = 0x001, 0x002, 0x004
IN_CLOSE_WRITE, IN_OPEN, IN_MOVED_TO, IN_CREATE, IN_DELETE = 0x008, 0x020, 0x080, 0x100, 0x200
_ALL = IN_ACCESS | IN_MODIFY | IN_CLOSE_WRITE | IN_OPEN | IN_MOVED_TO | IN_CREATE | IN_DELETE
_NAMES = {
    IN_ACCESS: "read",
    IN_MODIFY: "written",
    IN_CLOSE_WRITE: "written",
    IN_OPEN: "opened",
    IN_MOVED_TO: "created",
    IN_CREATE: "created",
    IN_DELETE: "deleted",
}
_EVENT = struct.Struct("iIII")


def available() -> bool:
    return os.name == "posix" and hasattr(ctypes.CDLL(None), "inotify_init1")


class Watch:
    """Watches every folder under ``root`` (``root`` included) for opens, reads, writes,
    creations and deletions of its entries; :meth:`events` lists what happened since."""

    def __init__(self, root: Path) -> None:
        self.libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self.libc.inotify_init1(os.O_NONBLOCK)
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "inotify_init1 failed")
        self.folders: dict[int, Path] = {}
        for folder in [root, *(p for p in root.rglob("*") if p.is_dir())]:
            wd = self.libc.inotify_add_watch(self.fd, os.fsencode(folder), _ALL)
            if wd < 0:
                raise OSError(ctypes.get_errno(), f"inotify_add_watch {folder}")
            self.folders[wd] = folder

    def events(self) -> list[str]:
        """``"<path> <what>"`` for every event since the last call."""
        out = []
        while True:
            try:
                data = os.read(self.fd, 1 << 16)
            except BlockingIOError:
                return out
            offset = 0
            while offset < len(data):
                wd, mask, _, size = _EVENT.unpack_from(data, offset)
                name = data[offset + _EVENT.size : offset + _EVENT.size + size].rstrip(b"\0")
                offset += _EVENT.size + size
                what = [v for k, v in _NAMES.items() if mask & k]
                path = self.folders.get(wd, Path("?")) / os.fsdecode(name)
                out.append(f"{path} {'/'.join(dict.fromkeys(what))}")

    def close(self) -> None:
        os.close(self.fd)

    def __enter__(self) -> Watch:
        self.events()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
