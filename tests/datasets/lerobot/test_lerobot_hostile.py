"""LeRobot datasets that are hostile, or change while they load (issue 42, findings 5-7).

* Finding 5, sizes a file declares: a path template asking for a gigabyte of format
  width, a PNG whose header declares 13000 x 13000 pixels in a few kilobytes. Each load
  runs in a child process whose address space is capped at what it holds after its
  imports plus 1.5 GiB, so that a load taking memory first fails with MemoryError instead
  of eating the machine; it must be refused with a ValueError, at once.
* Finding 6, files that change during the load, with real processes: a data file flipped
  between the real file and a symbolic link to a decoy outside (watched with inotify:
  nothing there may be opened or read, and no load returns the decoy's values), a FIFO in
  place of a data file (a load in a child process, bounded in time), and readers loading
  while a writer replaces the dataset again and again (no load may call it damaged).
* Finding 7, messages: a truncated data file names itself, a 10,000-character feature
  name and JSON nested 100,000 deep each give one clear ValueError naming the file.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import struct
import subprocess
import sys
import textwrap
import time
import warnings
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

import imitrl
from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot
from tests import _child, _watch
from tests._lerobot_files import episodes_data, write_v21, write_v30
from tests._lerobot_videos import add_cameras_v30
from tests.datasets.test_datasets_faults import _rows, _same

FORK = multiprocessing.get_context("fork")
SRC = str(Path(imitrl.__file__).resolve().parents[1])
"""the imitrl under test, for child processes"""
EPISODE_1 = "data/chunk-000/episode_000001.parquet"
V3_DATA = "data/chunk-000/file-000.parquet"


def _load(root, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(root, **kwargs)


def _edit_info(root: Path, edit) -> None:
    info = json.loads((root / "meta/info.json").read_text())
    edit(info)
    (root / "meta/info.json").write_text(json.dumps(info))


# ------------------------------------------------- finding 5: sizes a file declares
_CAPPED = r"""
import json, resource, sys, time, warnings
sys.path.insert(0, sys.argv[2])
from imitrl.datasets import load_lerobot
warnings.simplefilter("ignore")
with open("/proc/self/status") as f:
    held = next(int(line.split()[1]) << 10 for line in f if line.startswith("VmSize:"))
cap = held + (3 << 29)  # what the imports hold + 1.5 GiB
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
start = time.perf_counter()
try:
    load_lerobot(sys.argv[1], images="load")
    out = {"error": None}
except BaseException as err:  # MemoryError is what this test exists to catch
    out = {"error": type(err).__name__, "message": str(err)[:3000]}
out["seconds"] = time.perf_counter() - start
out["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def _capped_load(root: Path) -> dict:
    """``load_lerobot(root, images="load")`` in a child process capped at 1.5 GiB more
    than its imports hold: ``{"error", "message", "seconds", "peak_mib"}``."""
    done = _child.run(
        [sys.executable, "-c", textwrap.dedent(_CAPPED), str(root), SRC],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _v21_wide_data_path(tmp_path: Path) -> Path:
    root = write_v21(tmp_path / "ds", episodes_data([5, 6]))
    wide = "data/chunk-{episode_chunk:03d}/episode_{episode_index:0999999999d}.parquet"
    _edit_info(root, lambda info: info.update(data_path=wide))
    return root


def _v30_wide_video_path(tmp_path: Path) -> Path:
    root = write_v30(tmp_path / "ds", episodes_data([5, 6]), files=[(0, 0), (0, 0)])
    frames = [np.zeros((5, 16, 16, 3), np.uint8), np.zeros((6, 16, 16, 3), np.uint8)]
    add_cameras_v30(
        root, {"observation.images.cam": frames}, files=[(0, 0), (0, 0)], codec="libx264"
    )
    wide = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:0999999999d}.mp4"
    _edit_info(root, lambda info: info.update(video_path=wide))
    return root


@pytest.mark.parametrize("make", [_v21_wide_data_path, _v30_wide_video_path])
def test_a_huge_format_width_in_a_path_template_is_refused_before_memory_is_taken(tmp_path, make):
    """``{episode_index:0999999999d}`` would format a 1 GB file name (5.3 GB taken, then a
    bare MemoryError, before)."""
    out = _capped_load(make(tmp_path))
    assert out["error"] == "ValueError", out
    assert "info.json" in out["message"] and "format width past 32" in out["message"], out
    assert out["seconds"] < 5, out


def _grey_png(height: int, width: int) -> bytes:
    """A 1-bit grey PNG, every pixel 0: 13000 x 13000 of them deflate into 20 KB."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data)
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    row = b"\0" * (1 + (width + 7) // 8)
    deflate = zlib.compressobj(9)
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_a_png_declaring_huge_dimensions_is_refused_before_it_is_decoded(tmp_path):
    """Four frames of a 13000 x 13000 PNG, declared so in ``info.json`` too: 80 KB of
    parquet that decoded to 6 GB before; refused from its header now
    (``MAX_IMAGE_PIXELS``)."""
    root = write_v30(
        tmp_path / "ds", episodes_data([2, 2], image=(4, 4)), files=[(0, 0), (0, 0)], image=(4, 4)
    )
    png = _grey_png(13000, 13000)
    table = pq.read_table(root / V3_DATA)
    column = "observation.images.cam"
    kind = table.schema.field(column).type
    hostile = pa.array([{"bytes": png, "path": "frame.png"}] * table.num_rows, kind)
    table = table.set_column(table.schema.get_field_index(column), column, hostile)
    pq.write_table(table, root / V3_DATA)
    _edit_info(root, lambda info: info["features"][column].update(shape=[13000, 13000, 3]))
    out = _capped_load(root)
    assert out["error"] == "ValueError", out
    assert (
        "file-000.parquet: feature 'observation.images.cam': frame 0: its header" in out["message"]
    ), out
    assert "13000x13000" in out["message"] and "pixels an image may have" in out["message"], out
    assert out["seconds"] < 5, out


def test_a_png_holding_less_than_its_header_declares_is_refused_unread(tmp_path):
    """A 4000 x 4000 RGB PNG header over 2 KB of pixels: deflate expands at most 1032
    times, so the file cannot hold what it declares; refused before 48 MB are allocated
    for it (within ``MAX_IMAGE_PIXELS``, and the declared shape agrees)."""
    root = write_v30(
        tmp_path / "ds", episodes_data([2], image=(4, 4)), files=[(0, 0)], image=(4, 4)
    )
    png = bytearray(_grey_png(4000, 4000))
    png[24:26] = bytes([8, 2])  # 8-bit RGB: 48 MB of pixels, in the 1-bit image's 2 KB
    png[29:33] = struct.pack(">I", zlib.crc32(bytes(png[12:29])))
    table = pq.read_table(root / V3_DATA)
    column = "observation.images.cam"
    hostile = pa.array(
        [{"bytes": bytes(png), "path": "frame.png"}] * 2, table.schema.field(column).type
    )
    table = table.set_column(table.schema.get_field_index(column), column, hostile)
    pq.write_table(table, root / V3_DATA)
    _edit_info(root, lambda info: info["features"][column].update(shape=[4000, 4000, 3]))
    with pytest.raises(
        ValueError, match=r"frame 0: its header declares 4000x4000 .* more than its"
    ):
        _load(root, images="load")


def _inflate_rows(path: Path, rows: int) -> None:
    """``path``'s parquet rewritten as ``rows`` copies of its first row, in row groups of a
    million: a few hundred KB of zstd pages whose columns decode to ``rows`` * ~100
    bytes."""
    small = pq.read_table(path)
    group = small.slice(0, 1).take(pa.array(np.zeros(1 << 20, np.int64)))
    with pq.ParquetWriter(path.with_suffix(".new"), small.schema, compression="zstd") as out:
        for start in range(0, rows, 1 << 20):
            out.write_table(group.slice(0, min(1 << 20, rows - start)))
    path.with_suffix(".new").replace(path)


@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
def test_a_data_file_of_millions_more_rows_than_the_metadata_is_refused_unread(tmp_path, version):
    """Twelve million rows of one value in a few hundred KB of parquet, where the
    metadata (``info.json``, the episode table) says 5 frames, and no ``meta/imitrl.json``
    to check it by its checksum (any dataset imitrl did not write): on 7278396 the load
    read the whole file before it compared the counts (20 million rows: 4.6 GB; here past
    the cap, or long). Its footer is checked against the metadata first now."""
    if version == "v3.0":
        root = write_v30(tmp_path / "ds", episodes_data([3, 2]), files=[(0, 0), (0, 0)])
        data = root / V3_DATA
    else:
        root = write_v21(tmp_path / "ds", episodes_data([3, 2]))
        data = root / EPISODE_1
    _inflate_rows(data, 12_000_000)
    assert data.stat().st_size < 2_000_000 and not (root / "meta/imitrl.json").exists()
    out = _capped_load(root)
    assert out["error"] == "ValueError", out
    said = out["message"]
    if version == "v3.0":
        assert said.startswith(f"{root / 'data'}: the data files hold 12,000,000 frames"), out
        assert "the episode table covers 5; refused before reading them" in said, out
    else:
        assert said.startswith(f"{data}: episode 1 has 12000000 frames (its footer says)"), out
        assert "the episode metadata says 2; refused before reading it" in said, out
    assert out["seconds"] < 5, out


def test_the_footer_row_count_must_be_the_row_groups(tmp_path):
    """A footer is read as it declares (:func:`~imitrl.datasets._arrow.checked_rows`): the
    rows it declares must be its row groups' (each read as many as it declares)."""
    from imitrl.datasets._arrow import checked_rows

    class Meta:  # a footer declaring 5 rows over row groups of 3 and 20 million
        num_rows, num_row_groups = 5, 2

        def row_group(self, g):
            return type("Group", (), {"num_rows": (3, 20_000_000)[g]})

    hostile = type("File", (), {"metadata": Meta()})
    with pytest.raises(ValueError, match=r"x\.parquet: its footer declares 5 rows, its row groups "
                       r"20,000,003; refused before reading"):  # fmt: skip
        checked_rows(hostile, Path("x.parquet"))


# --------------------------------------- finding 6: files that change during a load
_FLIP = r"""
import os, sys
target, keep, decoy = sys.argv[1:4]
link, real = target + ".link-tmp", target + ".real-tmp"
while True:
    os.symlink(decoy, link)
    os.replace(link, target)
    os.link(keep, real)
    os.replace(real, target)
"""


def test_a_data_file_flipped_to_a_link_out_during_loads_is_never_read(tmp_path):
    """Another process flips a data file between the real file and a link to a decoy
    outside while loads run back to back: each load gets the real values or a refusal,
    and nothing outside is ever opened (7 of 300 loads read the decoy before: the check
    was on the path, the open later)."""
    root = write_v21(tmp_path / "ds", episodes_data([5, 6]))
    decoys = write_v21(tmp_path / "outside", episodes_data([5, 6], seed=9))
    honest = _load(root).rows.get(keys.OBSERVATION)
    keep = root / "data/chunk-000/.episode_000001.keep"  # the real file's second name
    os.link(root / EPISODE_1, keep)
    names = [str(root / EPISODE_1), str(keep), str(decoys / EPISODE_1)]
    flipper = subprocess.Popen([sys.executable, "-c", textwrap.dedent(_FLIP), *names])
    outcomes: dict[str, int] = {}
    wrong = 0
    try:
        with _watch.Watch(decoys) as watch:
            # 8 s, longer on a busy machine until 25 loads were tried (at most 60 s)
            start = time.monotonic()
            while time.monotonic() - start < 8 or (
                sum(outcomes.values()) < 25 and time.monotonic() - start < 60
            ):
                into = DemonstrationBuffer() if sum(outcomes.values()) % 2 else None
                try:
                    rows = _load(root, into=into).rows
                except ValueError as err:  # the link seen, or the file changing as it opened
                    refused = any(s in str(err) for s in ("symbolic link", "changed while"))
                    said = "refused" if refused else str(err)[:200]
                    outcomes[said] = outcomes.get(said, 0) + 1
                    continue
                outcomes["loaded"] = outcomes.get("loaded", 0) + 1
                wrong += not torch.equal(rows.get(keys.OBSERVATION), honest)
            events = watch.events()
    finally:
        flipper.kill()
        flipper.wait()
    assert events == [] and wrong == 0, (events[:5], wrong, outcomes)
    assert set(outcomes) <= {"loaded", "refused"}, outcomes
    assert sum(outcomes.values()) > 20, outcomes


_FIFO_LOAD = r"""
import sys, warnings
sys.path.insert(0, sys.argv[2])
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot
warnings.simplefilter("ignore")
try:
    load_lerobot(sys.argv[1], into=DemonstrationBuffer() if sys.argv[3] == "into" else None)
    print("loaded")
except ValueError as err:
    print("ValueError:", err)
"""

FIFOS = {
    "v2.1 data file": ("v2.1", EPISODE_1, "memory"),
    "v3.0 data file": ("v3.0", V3_DATA, "memory"),
    "v3.0 data file, streamed": ("v3.0", V3_DATA, "into"),
    "v3.0 episode table": ("v3.0", "meta/episodes/chunk-000/file-000.parquet", "memory"),
}


@pytest.mark.parametrize("case", list(FIFOS))
def test_a_fifo_in_place_of_a_file_is_refused_without_waiting(tmp_path, case):
    """A FIFO no process writes to: opening it for reading blocked the load forever."""
    version, name, how = FIFOS[case]
    episodes = episodes_data([5, 6])
    if version == "v2.1":
        root = write_v21(tmp_path / "ds", episodes)
    else:
        root = write_v30(tmp_path / "ds", episodes, files=[(0, 0), (0, 0)])
    (root / name).unlink()
    os.mkfifo(root / name)
    try:
        done = _child.run(
            [sys.executable, "-c", textwrap.dedent(_FIFO_LOAD), str(root), SRC, how],
            capture_output=True,
            text=True,
            timeout=15,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"load_lerobot waited on the FIFO {name} for 15 s")
    assert done.stdout.startswith(f"ValueError: {root / name}: a FIFO"), done.stdout + done.stderr


def _reader(path: str, stop, results) -> None:
    """Loads ``path`` until told to stop: how many loads gave a dataset the writer wrote,
    how many were told it was replaced while read, and every other outcome."""
    written = [_rows(seed) for seed in range(3)]
    counts = {"whole": 0, "replaced": 0}
    other: list[str] = []
    while not stop.is_set():
        try:
            rows = _load(path).rows
        except Exception as err:  # anything but "replaced while read" fails the test
            if isinstance(err, ValueError) and "replaced while" in str(err):
                counts["replaced"] += 1
            else:
                other.append(f"{type(err).__name__}: {err}"[:300])
            continue
        if any(_same(rows, w) for w in written):
            counts["whole"] += 1
        else:
            other.append("a mix of datasets")
    results.put((counts, other))


def test_readers_during_a_hundred_replacements_never_call_the_dataset_damaged(tmp_path):
    """Two reader processes load while the dataset is replaced up to 100 times in 10 s
    (``save_lerobot(..., overwrite=True)``): each load returns one whole dataset or says
    it was replaced while read (24 of 362 loads failed calling the data damaged before;
    1 to 9 of 200 to 1,600 loads here, hence 100 replacements rather than 40)."""
    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    stop, results = FORK.Event(), FORK.Queue()
    readers = [FORK.Process(target=_reader, args=(str(path), stop, results)) for _ in range(2)]
    for reader in readers:
        reader.start()
    deadline = time.monotonic() + 10
    try:
        for i in range(100):
            save_lerobot(_rows(i % 3), path, fps=10, overwrite=True)
            if time.monotonic() > deadline:
                break
    finally:
        stop.set()
    outcomes = [results.get(timeout=60) for _ in readers]
    for reader in readers:
        reader.join(timeout=60)
    whole = sum(counts["whole"] for counts, _ in outcomes)
    other = [said for _, said in outcomes for said in said]
    assert other == [], (len(other), other[:5], outcomes)
    assert whole > 20, outcomes


# --------------------------------------------------------- finding 7: clear messages
@pytest.mark.parametrize("into", [False, True], ids=["memory", "streamed"])
def test_a_truncated_data_file_is_named_not_blamed_on_the_episode_table(tmp_path, into):
    root = write_v30(tmp_path / "ds", episodes_data([4, 3]), files=[(0, 0), (0, 0)])
    data = root / V3_DATA
    data.write_bytes(data.read_bytes()[:2000])
    buffer = DemonstrationBuffer() if into else None
    with pytest.raises(ValueError) as refused:
        _load(root, into=buffer)
    said = str(refused.value)
    assert said.startswith(f"{data}: not a readable parquet file"), said
    assert "meta/episodes" not in said, said


def test_a_ten_thousand_character_feature_name_is_refused_in_one_line(tmp_path):
    root = write_v30(tmp_path / "ds", episodes_data([4, 3]), files=[(0, 0), (0, 0)])
    name = "observation." + "x" * 10_000
    _edit_info(root, lambda info: info["features"].update({name: info["features"]["action"]}))
    with pytest.raises(ValueError) as refused:
        _load(root)
    said = str(refused.value)
    assert said.startswith(f"{root / 'meta/info.json'}: feature name 'observation.xxx"), said
    assert "longer than the 249 bytes a LeRobot feature name may hold" in said, said
    assert len(said) < 500, len(said)


def _deep(depth: int) -> str:
    return "[" * depth + "]" * depth


def _saved(tmp_path: Path) -> Path:
    return save_lerobot(_rows(0), tmp_path / "ds", fps=10)


def _v21(tmp_path: Path) -> Path:
    return write_v21(tmp_path / "ds", episodes_data([4, 3]))


DEEP = {  # file -> the dataset it is made deep in
    "meta/info.json": _v21,
    "meta/episodes.jsonl": _v21,
    "meta/tasks.jsonl": _v21,
    "meta/stats.json": _saved,  # LeRobot rewrites it in place: checked as its statistics
    "meta/imitrl.json": _saved,
}


@pytest.mark.parametrize("name", list(DEEP))
def test_json_nested_a_hundred_thousand_deep_is_refused_naming_its_file(tmp_path, name):
    """A bare RecursionError before."""
    root = DEEP[name](tmp_path)
    (root / name).write_text(_deep(100_000) + "\n")
    with pytest.raises(ValueError, match=r"nested (too deeply|more than 32 levels)") as refused:
        _load(root)
    assert str(refused.value).startswith(str(root / name)), refused.value


def test_json_nested_past_the_bound_is_refused_where_it_would_be_walked(tmp_path):
    """``stats.json`` nested 40 deep parses, but its checks walk it: refused by its
    depth (``MAX_JSON_DEPTH``), as every metadata file is."""
    root = _saved(tmp_path)
    stats = json.loads((root / "meta/stats.json").read_text())
    first = next(iter(stats.values()))
    first["min"] = json.loads(_deep(40))
    (root / "meta/stats.json").write_text(json.dumps(stats))
    with pytest.raises(ValueError, match=r"stats\.json: JSON nested more than 32 levels deep"):
        _load(root)
