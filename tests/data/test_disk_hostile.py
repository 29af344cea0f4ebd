"""A disk buffer's directory is hostile on resume: its layout names nothing outside it.

``DemonstrationBuffer(path=..., resume=True)`` reads ``imitrl_buffer.json``, whose
``columns[].file`` name the files it maps read-write (:mod:`imitrl.data.disk`). A layout
that names a file outside ``storage/`` (an absolute path, ``..``), a link or a hard link
planted at a column file, or a capacity past the bytes the files hold is refused, and the
file it pointed to is neither read, grown nor written. A FIFO or a link to ``/dev/zero``
at the layout is refused at once (a child process under a time and memory limit).
"""

from __future__ import annotations

import json
import os
import sys
import textwrap
from pathlib import Path

import pytest

import imitrl
from imitrl.data import DemonstrationBuffer
from imitrl.fs import PlantedLinkError
from tests import _child
from tests.data.test_disk import cartpole_rows

SRC = str(Path(imitrl.__file__).resolve().parents[1])
SECRET = b"SECRET KEY MATERIAL " * 10 + b"\n"  # 201 bytes: room for the 12 rows' observations


def _stored(path: Path) -> dict:
    """A disk buffer of 12 rows at ``path`` (its lock released); its layout."""
    buf = DemonstrationBuffer(path=path, capacity=16)
    buf.extend(cartpole_rows(12))
    del buf  # its lock released
    return json.loads((path / "imitrl_buffer.json").read_text())


def _edit(path: Path, layout: dict, column: str, file: str) -> None:
    for c in layout["columns"]:
        if c["key"] == column.split("."):
            c["file"] = file
    (path / "imitrl_buffer.json").write_text(json.dumps(layout))


def _victim(tmp_path: Path) -> Path:
    victim = tmp_path / "victim.txt"
    victim.write_bytes(SECRET)
    return victim


@pytest.mark.parametrize(
    "file",
    ["{victim}", "../victim.txt", "storage/../../victim.txt", "storage/next/../../../victim.txt"],
)
def test_a_layout_naming_a_file_outside_storage_is_refused_and_the_file_untouched(tmp_path, file):
    victim = _victim(tmp_path)
    path = tmp_path / "buf"
    _edit(path, _stored(path), "observation", file.format(victim=victim))
    refused = "not a readable disk buffer layout .*(must lie in storage/|cannot name a file)"
    with pytest.raises(ValueError, match=refused):
        DemonstrationBuffer(path=path, resume=True)
    assert victim.read_bytes() == SECRET  # before the fix: grown to 16 rows, then written


@pytest.mark.parametrize("planted", ["link", "folder link", "hard link"])
def test_a_link_or_a_hard_link_in_storage_is_refused_and_its_target_untouched(tmp_path, planted):
    victim = _victim(tmp_path)
    path = tmp_path / "buf"
    _stored(path)
    column = path / "storage" / "observation.memmap"
    if planted == "folder link":  # storage/next -> a folder outside holding reward.memmap
        outside = tmp_path / "outside"
        outside.mkdir()
        victim = victim.rename(outside / "reward.memmap")
        column = path / "storage" / "next"
        for f in column.iterdir():
            f.unlink()
        column.rmdir()
    else:
        column.unlink()
    if planted == "hard link":
        os.link(victim, column)
    else:
        column.symlink_to(victim.parent if planted == "folder link" else victim)
    with pytest.raises(PlantedLinkError, match=r"symbolic link|hard link"):
        DemonstrationBuffer(path=path, resume=True)
    assert victim.read_bytes() == SECRET and victim.stat().st_size == len(SECRET)


@pytest.mark.parametrize("edit", ["capacity past the files", "rows without columns"])
def test_rows_and_capacity_past_the_files_bytes_are_refused_and_no_file_grows(tmp_path, edit):
    path = tmp_path / "buf"
    layout = _stored(path)
    files = {f: f.stat().st_size for f in (path / "storage").rglob("*.memmap")}
    if edit == "capacity past the files":  # 16 rows stored: 1e8 would be 1.6 GB of obs
        layout["capacity"] = 10**8
    else:
        layout["columns"] = []
    (path / "imitrl_buffer.json").write_text(json.dumps(layout))
    with pytest.raises(ValueError, match=r"a capacity of 100000000 rows needs|no column file"):
        DemonstrationBuffer(path=path, resume=True)
    assert {f: f.stat().st_size for f in files} == files  # before the fix: truncated longer


_RESUME = r"""
import json, resource, sys, warnings
sys.path.insert(0, sys.argv[1])
warnings.simplefilter("ignore")
from imitrl.data import DemonstrationBuffer
with open("/proc/self/status") as f:
    held = next(int(line.split()[1]) << 10 for line in f if line.startswith("VmSize:"))
resource.setrlimit(resource.RLIMIT_AS, (held + (1 << 30),) * 2)  # the imports + 1 GiB
out = {}
for path in sys.argv[2:]:
    try:
        DemonstrationBuffer(path=path, resume=True)
        out[path] = "resumed"
    except BaseException as err:  # MemoryError is what this test exists to catch
        out[path] = f"{type(err).__name__}: {err}"
print(json.dumps(out))
"""


def test_a_fifo_or_a_link_at_the_layout_or_a_column_is_refused_at_once(tmp_path):
    paths = {case: tmp_path / case for case in ("fifo", "zero", "big", "fifo column")}
    for path in paths.values():
        _stored(path)
    os.unlink(paths["fifo"] / "imitrl_buffer.json")
    os.mkfifo(paths["fifo"] / "imitrl_buffer.json")  # before the fix: blocked forever
    os.unlink(paths["zero"] / "imitrl_buffer.json")
    os.symlink("/dev/zero", paths["zero"] / "imitrl_buffer.json")  # read without bound
    os.truncate(paths["big"] / "imitrl_buffer.json", (16 << 20) + 1)  # sparse, past the limit
    os.unlink(paths["fifo column"] / "storage" / "observation.memmap")
    os.mkfifo(paths["fifo column"] / "storage" / "observation.memmap")
    done = _child.run(
        [sys.executable, "-c", textwrap.dedent(_RESUME), SRC, *map(str, paths.values())],
        capture_output=True, text=True, timeout=30,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    expected = {
        "fifo": "a FIFO",
        "zero": "a symbolic link",
        "big": "more than the 16,777,216",
        "fifo column": "not a regular file",
    }
    for case, text in expected.items():
        message = got[str(paths[case])]
        assert message.startswith(("ValueError", "PlantedLinkError")), (case, message)
        assert text in message, (case, message)
