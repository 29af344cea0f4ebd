"""Minari files declaring more than their bytes hold (:mod:`imitrl.datasets.minari._bounds`).

* Issue 42, finding 5: a file declaring more values than its bytes hold (an HDF5 dataset
  with no chunk written, a parquet footer's run-length rows, a compressed Arrow buffer)
  is refused before anything is allocated, naming the file, the episode, the array and
  both sizes.
* The dataset readers' review, finding 10: the arrays that declare more than their bytes
  allow may do so up to ``FLOOR_BYTES`` for the whole load, not each: twelve episodes of
  HDF5 arrays each just under it (a 41 KB file) loaded 48 million rows, 5.5 GB; forty
  parquet episodes each under it, as much.

Each load runs in a subprocess under ``RLIMIT_AS`` (1 GiB above what its imports
mapped), so the old code's allocation fails there instead of on the machine.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.ipc as ipc
import pyarrow.parquet as pq
import pytest

from tests.datasets.minari.test_minari import DISCRETE2, _episode, _write
from tests.datasets.minari.test_minari_hostile import _meta, _python

# ------------------------------- finding 5: sizes bounded by the bytes, per array
_BOUNDED_LOAD = r"""
import json, resource, sys, time, warnings
import torch
torch.set_num_threads(1)
warnings.simplefilter("ignore")
from imitrl.datasets import load_minari
import h5py, pyarrow.parquet, pyarrow.ipc  # every reader's import mapped before the limit

def mapped(field):
    for line in open("/proc/self/status"):
        if line.startswith(field):
            return int(line.split()[1]) * 1024

resource.setrlimit(resource.RLIMIT_AS, (mapped("VmSize:") + (1 << 30),) * 2)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")  # the peak resident size (VmHWM) starts again from here
before, start = mapped("VmRSS:"), time.perf_counter()
try:
    load_minari(sys.argv[1])
    out = {"error": None}
except BaseException as err:
    out = {"error": type(err).__name__, "message": str(err)[:2000]}
out["seconds"] = time.perf_counter() - start
out["grew_mb"] = (mapped("VmHWM:") - before) / 2**20
print(json.dumps(out))
"""


def _bounded_load(root: Path) -> dict:
    """``load_minari(root)`` in a subprocess under the memory limit; pyarrow on the system
    allocator there (jemalloc and mimalloc reserve arenas far beyond what they use,
    which a limit on the address space refuses at the first allocation)."""
    done = _python(_BOUNDED_LOAD, str(root), timeout=300, ARROW_DEFAULT_MEMORY_POOL="system")
    assert done.stdout.strip(), done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    print(out)  # the measured refusal time and memory, with -s
    return out


@pytest.mark.parametrize("compression", [None, "gzip"])
def test_an_hdf5_dataset_declaring_more_than_it_stores_is_refused_first(tmp_path, compression):
    """2 GB of observations declared by a file of a few KB (chunked, no chunk written: HDF5
    would hand back fill values); on d6e5639: MemoryError under the limit."""
    root = _write(tmp_path / "ds", [_episode(3, 0)])
    steps = 500_000_000 // 4
    with h5py.File(root / "data/main_data.hdf5", "a") as f:
        group = f["episode_0"]
        del group["observations"]
        group.create_dataset(
            "observations",
            shape=(steps + 1, 4),
            dtype="f4",
            chunks=(65536, 4),
            compression=compression,
        )
        group.attrs["total_steps"] = steps
        for name in ("actions", "rewards", "terminations", "truncations"):
            del group[name]
            group.create_dataset(name, shape=(steps,), dtype="i8" if name == "actions" else "f8")
    meta = json.loads((root / "data/metadata.json").read_text())
    (root / "data/metadata.json").write_text(json.dumps({**meta, "total_steps": steps}))
    assert (root / "data/main_data.hdf5").stat().st_size < 100_000
    out = _bounded_load(root)
    assert out["error"] == "ValueError", out
    message = out["message"]
    assert str(root / "data/main_data.hdf5") in message and "episode_0" in message, message
    assert "observations: declares 2,000,000,016 bytes" in message, message
    assert "its file stores 0 bytes" in message and "refused before reading" in message, message
    assert out["seconds"] < 5 and out["grew_mb"] < 200, out


def _columns(rows: int, infos: int) -> pa.Table:
    """``rows`` steps of zeros in Minari's columns (Discrete observations and actions),
    each column one value: a run-length page or a zstd frame declares them all in a few
    bytes; ``infos`` zeros a step in an ``infos`` column too, when not 0."""
    dtypes = {"observations": "i8", "actions": "i8", "rewards": "f8"}
    dtypes |= {"terminations": bool, "truncations": bool}
    columns = {name: pa.array(np.zeros(rows, dtype)) for name, dtype in dtypes.items()}
    if infos:
        values = pa.array(np.zeros(rows * infos, "i8"))
        columns["infos"] = pa.FixedSizeListArray.from_arrays(values, infos)
    fields = [pa.field(name, column.type, nullable=False) for name, column in columns.items()]
    return pa.table(list(columns.values()), schema=pa.schema(fields))


BOMBS = {
    "parquet rows": ("parquet", 60_000_000, 0),
    "arrow rows": ("arrow", 60_000_000, 0),
    "arrow infos": ("arrow", 1_000, 200_000),
}
"""format, rows, zeros a step in ``infos``: 1.56 GB of step columns once loaded (26
bytes a step) from about 1 MB of parquet or 50 KB of arrow; 1.6 GB of infos from 50 KB"""


def _columnar_bomb(root: Path, case: str) -> Path:
    fmt, rows, infos = BOMBS[case]
    data = root / "data"
    (data / "0").mkdir(parents=True)
    meta = _meta(fmt, rows - 1, obs_space=DISCRETE2)
    (data / "metadata.json").write_text(json.dumps(meta))
    table, part = _columns(rows, infos), data / "0" / f"part-0.{fmt}"
    if fmt == "parquet":
        pq.write_table(
            table,
            part,
            compression="zstd",
            row_group_size=rows,
            data_page_size=1 << 30,
            write_batch_size=1 << 24,
            use_dictionary=["observations", "actions", "rewards"],
            column_encoding={"terminations": "RLE", "truncations": "RLE"},
        )
    else:
        options = ipc.IpcWriteOptions(compression="zstd")
        with ipc.new_file(part, table.schema, options=options) as writer:
            writer.write_table(table)
    return part


@pytest.mark.parametrize("case", list(BOMBS))
def test_a_columnar_episode_declaring_more_than_its_bytes_hold_is_refused_first(tmp_path, case):
    """Sixty million rows of zeros in a few bytes of run-length pages (parquet) or zstd
    frames (arrow), or a thousand rows with 1.6 GB of zstd-compressed infos; on d6e5639
    pyarrow allocated them all (under the limit: "not a readable file (malloc ...
    failed)")."""
    part = _columnar_bomb(tmp_path / "ds", case)
    size = part.stat().st_size
    assert size < 2_000_000
    out = _bounded_load(tmp_path / "ds")
    assert out["error"] == "ValueError", out
    message = out["message"]
    assert f"{part} (episode 0): " in message, message
    steps = "60,000,000 rows of observations, actions, rewards, terminations, truncations"
    declared = "its compressed buffers" if case == "arrow infos" else steps
    assert f"{declared}: declares " in message, message
    assert f"its file stores {size:,} bytes" in message, message
    assert "refused before reading" in message, message
    assert out["seconds"] < 5 and out["grew_mb"] < 200, out


# ------------------------- finding 10: sizes beyond the bytes, for the whole load
def _hdf5_under_the_floor(root: Path, episodes: int, steps: int) -> Path:
    """``episodes`` groups whose arrays each declare just under ``FLOOR_BYTES`` (``steps``
    steps; chunked, no chunk written: HDF5 hands back fill values), in a file of a few KB."""
    _write(root, [_episode(3, e) for e in range(episodes)])
    path = root / "data/main_data.hdf5"
    with h5py.File(path, "a") as f:
        for e in range(episodes):
            group = f[f"episode_{e}"]
            group.attrs["total_steps"] = steps
            dtypes = {"observations": "f4", "actions": "i8", "rewards": "f8"}
            dtypes |= {"terminations": bool, "truncations": bool}
            for name, dtype in dtypes.items():
                del group[name]
                shape = (steps + 1, 4) if name == "observations" else (steps,)
                group.create_dataset(name, shape=shape, dtype=dtype, chunks=(1 << 16, *shape[1:]))
    meta = json.loads((root / "data/metadata.json").read_text())
    (root / "data/metadata.json").write_text(json.dumps({**meta, "total_steps": episodes * steps}))
    return path


def _parquet_under_the_floor(root: Path, episodes: int, steps: int) -> Path:
    """``episodes`` folders each holding the same parquet part of ``steps + 1`` rows of
    zeros (a few KB of run-length pages), whose rows and values each declare just under
    half ``FLOOR_BYTES``."""
    data = root / "data"
    (data / "0").mkdir(parents=True)
    meta = {**_meta("parquet", episodes * steps, DISCRETE2), "total_episodes": episodes}
    (data / "metadata.json").write_text(json.dumps(meta))
    dtypes = {"observations": "i8", "actions": "i8", "rewards": "f8"}
    dtypes |= {"terminations": bool, "truncations": bool}
    table = pa.table({name: np.zeros(steps + 1, dtype) for name, dtype in dtypes.items()})
    part = data / "0/part-0.parquet"
    pq.write_table(table, part, compression="zstd", row_group_size=steps + 1)
    for e in range(1, episodes):
        (data / str(e)).mkdir()
        shutil.copyfile(part, data / str(e) / "part-0.parquet")
    return part


UNDER_THE_FLOOR = {
    # 12 episodes of 136 MB of arrays (the largest 64,000,016 bytes): 1.6 GB
    "hdf5": (_hdf5_under_the_floor, 12, 4_000_000),
    # 40 episodes of 1.2 million rows, 31 MB of steps and 31 MB of values each: 2.5 GB
    "parquet": (_parquet_under_the_floor, 40, 1_200_000),
}


@pytest.mark.parametrize("fmt", list(UNDER_THE_FLOOR))
def test_arrays_each_under_the_floor_are_refused_once_they_pass_it_together(tmp_path, fmt):
    """On 7278396 each array was checked alone against ``FLOOR_BYTES`` and passed: the load
    went on to the memory limit (MemoryError here; 5.5 GB unbounded). Now the arrays
    beyond their bytes share one floor: refused at the first array past it, naming what
    the arrays before it took."""
    make, episodes, steps = UNDER_THE_FLOOR[fmt]
    path = make(tmp_path / "ds", episodes, steps)
    assert path.stat().st_size < 200_000
    out = _bounded_load(tmp_path / "ds")
    assert out["error"] == "ValueError", out
    message = out["message"]
    if fmt == "hdf5":  # the first episode's observations took 64,000,016 bytes
        assert f"{path}: episode_0: actions: declares 32,000,000 bytes" in message, message
        took = "64,000,016"
    else:  # the first episode's rows and values took 31,200,026 bytes each
        first = tmp_path / "ds/data/1/part-0.parquet"
        assert f"{first} (episode 1): 1,200,001 rows of observations" in message, message
        took = "62,400,052"
    beyond = f"the arrays read before it took {took} of the 67,108,864 bytes a load may declare"
    assert beyond in message and "refused before reading" in message, message
    assert out["seconds"] < 5 and out["grew_mb"] < 200, out
