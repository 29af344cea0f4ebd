"""Minari datasets, hostile and on a full disk (issue 42, findings 3, 5, 6 and 7).

* Finding 3: ``save_minari`` meeting a full disk (a real 256 KiB tmpfs where one can be
  mounted, an injected ``ENOSPC`` everywhere) raises ``DiskFullError`` and leaves the
  dataset there whole; HDF5's own failing close used to end the process with SIGSEGV.
* Finding 5: a file declaring more values than its bytes hold is refused before anything
  is allocated: in ``tests/datasets/minari/test_bounds.py``, with the sizes the arrays of a whole load
  declare.
* Finding 6: every file is opened once, by descriptor, inside the dataset folder: a FIFO
  in place of a data file is refused at once (it used to hang), a link swapped in after
  the folder was checked is refused, and a load racing ``save_minari(...,
  overwrite=True)`` in another process reads one dataset whole or says it was replaced.
* Finding 7: JSON nested too deeply (metadata, a serialized space, an episode's
  metadata, the dataset an overwrite replaces) is refused by name, not a RecursionError.
"""

from __future__ import annotations

import errno
import json
import multiprocessing
import os
import re
import shlex
import shutil
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pyarrow as pa
import pyarrow.ipc as ipc
import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.datasets import load_minari, save_minari
from imitrl.fs import DiskFullError
from tests import _child
from tests.datasets.minari.test_minari import BOX4, DISCRETE2, _episode, _write

torch.set_num_threads(1)
FORK = multiprocessing.get_context("fork")
SRC = next(p for p in sys.path if (Path(p) / "imitrl").is_dir())
ROOT = str(Path(__file__).resolve().parents[3])
SPACES = {
    "observation_space": gym.spaces.Box(0.0, 1.0, (4,), np.float32),
    "action_space": gym.spaces.Discrete(2),
}


def _rows(lengths: list[int], seed: int = 0) -> TensorDict:
    """Episodes of ``lengths[e]`` steps (Box(4) observations in [0, 1), Discrete(2)
    actions), with every row's ``("next", "observation")``, as ``save_minari`` takes them."""
    g = torch.Generator().manual_seed(seed)
    n = sum(lengths)
    obs = torch.rand(n + len(lengths), 4, generator=g)  # one final observation per episode
    cur = torch.cat([torch.arange(k) + sum(lengths[:e]) + e for e, k in enumerate(lengths)])
    last = torch.cat([torch.arange(k) == k - 1 for k in lengths]).reshape(-1, 1)
    return TensorDict(
        {
            keys.OBSERVATION: obs[cur],
            keys.EXPERT_ACTION: torch.randint(0, 2, (n,), generator=g),
            keys.EPISODE: torch.cat([torch.full((k,), e) for e, k in enumerate(lengths)]),
            keys.STEP: torch.cat([torch.arange(k) for k in lengths]),
            keys.NEXT: {
                keys.OBSERVATION: obs[cur + 1],
                keys.REWARD: torch.rand(n, 1, generator=g),
                keys.DONE: last,
                keys.TERMINATED: last,
                keys.TRUNCATED: torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )


def _quiet_load(path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_minari(path, **kwargs)


def _python(script: str, *args: str, timeout: float, **env: str) -> subprocess.CompletedProcess:
    """``script`` run by this interpreter with ``sys.argv[1:] = args``, imitrl (the one
    under test) and the tests importable, and ``env`` added to the environment."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([SRC, ROOT]), "OMP_NUM_THREADS": "1", **env}
    return _child.run(
        [sys.executable, "-c", textwrap.dedent(script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=ROOT,  # its ``tests`` package is this one
    )


# -------------------------------------------------------------- finding 3: a full disk
_FULL_DISK = r"""
import json, sys, warnings
import torch
torch.set_num_threads(1)
warnings.simplefilter("ignore")
from imitrl.datasets import load_minari, save_minari
from imitrl.fs import DiskFullError
from tests.datasets.minari.test_minari_hostile import SPACES as spaces, _rows

disk, out = sys.argv[1], {}
small, big = _rows([5, 6]), _rows([1000] * 12, seed=1)  # 0.4 MB: more than 256 KiB
save_minari(small, disk + "/ds", **spaces)

def attempt(name, path, overwrite, intact):
    try:
        save_minari(big, path, overwrite=overwrite, **spaces)
        out[name] = "no error"
    except DiskFullError as err:
        out[name] = {"message": str(err), "errno": err.errno, "intact": intact()}
    except BaseException as err:
        out[name] = f"{type(err).__name__}: {err}"

attempt("overwrite", disk + "/ds", True,
        lambda: len(load_minari(disk + "/ds", next_observation=True).rows) == 11)
attempt("new", disk + "/new", False, lambda: not __import__("os").path.exists(disk + "/new"))
out["left"] = sorted(__import__("os").listdir(disk))
print(json.dumps(out))
"""


def _on_a_small_tmpfs(tmp_path: Path, script: str) -> subprocess.CompletedProcess:
    """``script`` run with a 256 KiB tmpfs mounted at its first argument, in a mount
    namespace of its own (as root, or as a user mapped to root: the pattern of
    ``test_writers_concurrency._in_a_small_tmpfs``); skipped where neither may mount.
    ``MOUNTED`` on stderr tells a failed mount from a failed script."""
    disk = tmp_path / "disk"
    disk.mkdir()
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare(1) to mount a small file system")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([SRC, ROOT]), "OMP_NUM_THREADS": "1"}
    inner = (
        f"mount -t tmpfs -o size=256k tmpfs {disk} && echo MOUNTED >&2 && "
        f"{sys.executable} -c {shlex.quote(textwrap.dedent(script))} {disk}"
    )
    for flags in (["-m"], ["-rm"]):
        done = subprocess.run(
            [unshare, *flags, "sh", "-c", inner],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
            cwd=ROOT,  # its ``tests`` package is this one
        )
        if "MOUNTED" in done.stderr:
            return done
    pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()[-300:]}")


def test_save_minari_on_a_full_tmpfs_raises_disk_full_and_keeps_the_dataset(tmp_path):
    """On d6e5639 the writer process died of SIGSEGV (exit 139) in h5py's close."""
    done = _on_a_small_tmpfs(tmp_path, _FULL_DISK)
    assert done.returncode == 0, f"exit {done.returncode} (139: SIGSEGV): {done.stderr[-2000:]}"
    for noise in ("Traceback", "Exception ignored", "Segmentation fault"):
        assert noise not in done.stderr, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    disk = tmp_path / "disk"
    for name, where in (("overwrite", "ds"), ("new", "new")):
        got = out[name]
        assert isinstance(got, dict), (name, got)
        assert got["errno"] == errno.ENOSPC and got["intact"], (name, got)
        assert f"to {disk / where} (" in got["message"], got["message"]
    assert out["left"] == ["ds"], out  # no staging folder, no lock left behind


@pytest.mark.parametrize("fail_at", ["first write", "an episode", "the last writes"])
def test_an_injected_enospc_at_any_write_is_a_disk_full_error(tmp_path, monkeypatch, fail_at):
    """Where no tmpfs can be mounted: the HDF5 file's writes (``os.pwrite``) meet ENOSPC
    at the superblock, amid the episodes, or among the last (the close's metadata)."""
    small, big = _rows([5, 6]), _rows([3] * 2000, seed=1)  # HDF5 reads back as it writes
    probe = save_minari(big, tmp_path / "probe", **SPACES) / "data" / "main_data.hdf5"
    size = probe.stat().st_size
    room = {"first write": 0, "an episode": size // 2, "the last writes": size - 64}[fail_at]
    path = save_minari(small, tmp_path / "ds", **SPACES)
    written = [0]
    real = os.pwrite

    def pwrite(fd, data, offset):
        if written[0] + len(data) > room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written[0] += len(data)
        return real(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", pwrite)
    with pytest.raises(
        DiskFullError, match=re.escape(f"to {tmp_path / 'ds'} (") + ".*nothing was published"
    ):
        save_minari(big, path, overwrite=True, **SPACES)
    monkeypatch.undo()
    assert len(_quiet_load(path).rows) == 11
    assert sorted(os.listdir(tmp_path)) == ["ds", "probe"]


def test_after_a_failed_write_the_file_reads_back_what_went_to_memory(tmp_path, monkeypatch):
    """The file HDF5 writes through: once a write fails, later writes are kept in memory
    and every read sees the latest bytes, whether they reached the disk or not."""
    from imitrl.datasets.minari._hdf5_out import _Spilling

    fd = os.open(tmp_path / "f", os.O_RDWR | os.O_CREAT)
    file = _Spilling(fd)
    file.write(b"a" * 10)
    real = os.pwrite

    def full(fd, data, offset):
        real(fd, bytes(data[:3]), offset)  # part of it reaches the disk, then ENOSPC
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", full)
    file.seek(8)
    file.write(b"b" * 6)  # 8..14: fails, kept in memory
    file.seek(2)
    file.write(b"c" * 2)  # 2..4: in memory too (no write after the first failure)
    assert file.failed is not None and file.failed.errno == errno.ENOSPC
    file.seek(0)
    buffer = bytearray(20)
    assert file.readinto(buffer) == 14 and bytes(buffer[:14]) == b"aaccaaaabbbbbb"
    assert file.seek(0, os.SEEK_END) == 14
    os.close(fd)


def test_thousands_of_episodes_are_written_and_read_back_whole(tmp_path):
    """Not a finding: HDF5 reads back what it wrote on a file of a few thousand episodes
    (its metadata cache), so the file the writer hands it must read as well as write."""
    rows = _rows([3] * 2500, seed=2)
    loaded = _quiet_load(save_minari(rows, tmp_path / "ds", **SPACES), next_observation=True)
    assert torch.equal(loaded.rows[keys.OBSERVATION], rows[keys.OBSERVATION])
    assert torch.equal(loaded.rows[keys.NEXT, keys.OBSERVATION], rows[keys.NEXT, keys.OBSERVATION])


def _meta(fmt: str, steps: int, obs_space: dict = BOX4) -> dict:
    return {
        "total_episodes": 1,
        "total_steps": steps,
        "data_format": fmt,
        "observation_space": json.dumps(obs_space),
        "action_space": json.dumps(DISCRETE2),
        "minari_version": "0.5.4",
    }


# ------------------------------------------- finding 6: each file once, by descriptor
def _columnar(root: Path, fmt: str, lengths=(3, 4), seed: int = 0) -> Path:
    """A Minari arrow / parquet dataset laid out by hand as Minari 0.5 writes it: a folder
    per episode holding ``part-0.<fmt>`` (T + 1 rows, the last one padding) and
    ``metadata.json``."""
    data = root / "data"
    data.mkdir(parents=True)
    meta = {**_meta(fmt, sum(lengths)), "total_episodes": len(lengths)}
    (data / "metadata.json").write_text(json.dumps(meta))
    for e, n in enumerate(lengths):
        ep = _episode(n, seed + e)
        pad = lambda v: np.concatenate([v, v[-1:]])  # noqa: E731
        obs = pa.FixedSizeListArray.from_arrays(pa.array(ep["observations"].reshape(-1)), 4)
        table = pa.table(
            {
                "observations": obs,
                **{k: pad(ep[k]) for k in ("actions", "rewards", "terminations", "truncations")},
            }
        )
        (data / str(e)).mkdir()
        part = data / str(e) / f"part-0.{fmt}"
        if fmt == "parquet":
            pq.write_table(table, part)
        else:
            with ipc.new_file(part, table.schema) as writer:
                writer.write_table(table)
        (data / str(e) / "metadata.json").write_text(json.dumps({"id": e, "total_steps": n}))
    return root


_LOAD = r"""
import json, sys, warnings
warnings.simplefilter("ignore")
from imitrl.datasets import load_minari
try:
    out = {"rows": len(load_minari(sys.argv[1]).rows)}
except BaseException as err:
    out = {"error": type(err).__name__, "message": str(err)}
print(json.dumps(out))
"""

_FIFOS = {
    "hdf5 file": ("hdf5", "data/main_data.hdf5"),
    "hdf5 metadata.json": ("hdf5", "data/metadata.json"),
    "parquet part": ("parquet", "data/1/part-0.parquet"),
    "arrow part": ("arrow", "data/1/part-0.arrow"),
    "episode metadata.json": ("arrow", "data/1/metadata.json"),
}


@pytest.mark.parametrize("case", list(_FIFOS))
def test_a_fifo_in_place_of_a_data_file_is_refused_at_once(tmp_path, case):
    """On d6e5639 a FIFO part file hung the load (open(2) waits for a writer), a FIFO
    HDF5 file or metadata.json was reported as missing, a FIFO episode metadata.json
    was skipped."""
    fmt, name = _FIFOS[case]
    root = tmp_path / "ds"
    if fmt == "hdf5":
        _write(root, [_episode(3, 0), _episode(4, 1)])
    else:
        _columnar(root, fmt)
    (root / name).unlink()
    os.mkfifo(root / name)
    start = time.perf_counter()
    try:
        done = _python(_LOAD, str(root), timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the load hung on the FIFO {name}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out.get("error") == "ValueError", out
    assert f"{root / name}: a FIFO" in out["message"], out
    assert time.perf_counter() - start < 60


def _outside_copy(tmp_path: Path, fmt: str) -> Path:
    """Another dataset's file of the same kind, outside the one loaded (other values)."""
    if fmt == "hdf5":
        other = _write(tmp_path / "other", [_episode(3, 7), _episode(4, 8)])
        return other / "data/main_data.hdf5"
    return _columnar(tmp_path / "other", fmt, seed=7) / "data/1" / f"part-0.{fmt}"


@pytest.mark.parametrize("fmt", ["hdf5", "parquet"])
def test_a_link_swapped_in_after_the_folder_was_checked_is_refused(tmp_path, monkeypatch, fmt):
    """The dataset passes ``resolve_minari_root``'s check, then a data file becomes a link
    to a file outside; on d6e5639 the load followed it and returned the outside values."""
    import imitrl.datasets.minari as minari_module

    root = tmp_path / "ds"
    if fmt == "hdf5":
        _write(root, [_episode(3, 0), _episode(4, 1)])
        name = root / "data/main_data.hdf5"
    else:
        name = _columnar(root, fmt) / "data/1/part-0.parquet"
    outside = _outside_copy(tmp_path, fmt)
    real = minari_module.resolve_minari_root

    def checked_then_swapped(path):
        found = real(path)
        name.unlink()
        name.symlink_to(outside)
        return found

    monkeypatch.setattr(minari_module, "resolve_minari_root", checked_then_swapped)
    with pytest.raises(
        ValueError, match=re.escape(f"{name}: a symbolic link out of the dataset folder")
    ):
        _quiet_load(root)


def test_a_streamed_load_reads_in_its_second_pass_the_files_its_first_checked(
    tmp_path, monkeypatch
):
    """``load_minari(..., into=buffer)`` checks every episode, then reads them again to
    extend the buffer; the dataset is replaced in between (an exchange, the old folder
    removed, as ``save_minari(..., overwrite=True)`` does). On d6e5639 the second pass
    opened the new dataset's files by name and put rows no check had seen in the buffer."""
    import imitrl.datasets.minari._stream as stream_module
    from imitrl.data import DemonstrationBuffer
    from imitrl.fs.publish import exchange

    root = _columnar(tmp_path / "ds", "parquet")
    expected = _quiet_load(shutil.copytree(root, tmp_path / "copy")).rows
    other = _columnar(tmp_path / "other", "parquet", seed=7)  # same shapes, other values
    real = stream_module.check_pieces

    def checked_then_replaced(*args, **kwargs):
        frames = real(*args, **kwargs)
        assert exchange(other, root)
        shutil.rmtree(other)  # the old dataset, now at the other name
        return frames

    monkeypatch.setattr(stream_module, "check_pieces", checked_then_replaced)
    buffer = DemonstrationBuffer()
    _quiet_load(root, into=buffer)
    assert torch.equal(buffer.data[keys.OBSERVATION], expected[keys.OBSERVATION])
    assert torch.equal(buffer.data[keys.EXPERT_ACTION], expected[keys.EXPERT_ACTION])


def _replacer(path: str, rounds: int, started, done) -> None:
    """``save_minari(..., overwrite=True)`` of two datasets in turn."""
    versions = [_rows([5, 6]), _rows([9, 3, 4], seed=1)]
    started.set()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(rounds):
            save_minari(versions[i % 2], path, overwrite=True, **SPACES)
    done.set()


def test_a_load_racing_a_replacement_reads_one_dataset_whole_or_says_replaced(tmp_path):
    """Loads run while another process replaces the dataset again and again: each returns
    one version whole (11 or 16 rows, its own values) or says "replaced while"; on
    d6e5639 metadata.json of one version met the HDF5 file of the other ("metadata
    declares 2 episodes, the dataset holds 3") or a file vanished mid-load."""
    versions = [_rows([5, 6]), _rows([9, 3, 4], seed=1)]
    path = save_minari(versions[0], tmp_path / "ds", **SPACES)
    started, done = FORK.Event(), FORK.Event()
    writer = FORK.Process(target=_replacer, args=(str(path), 800, started, done))
    writer.start()
    outcomes: dict[str, int] = {}
    try:
        assert started.wait(timeout=60)
        deadline = time.monotonic() + 120
        while not done.is_set() and time.monotonic() < deadline:
            try:
                rows = _quiet_load(path, next_observation=True).rows
                match = [v for v in versions if len(v) == len(rows)]
                assert match and torch.equal(rows[keys.OBSERVATION], match[0][keys.OBSERVATION]), (
                    "a mixture of two versions"
                )
                outcomes[f"ok {len(rows)}"] = outcomes.get(f"ok {len(rows)}", 0) + 1
            except ValueError as err:
                kind = "replaced" if "replaced while" in str(err) else f"damaged: {err}"
                outcomes[kind] = outcomes.get(kind, 0) + 1
    finally:
        writer.join(timeout=120)
    print(outcomes)  # with -s: how the loads went
    damaged = {k: n for k, n in outcomes.items() if k.startswith("damaged")}
    assert not damaged, outcomes
    assert sum(n for k, n in outcomes.items() if k.startswith("ok")) >= 5, outcomes


# ------------------------------------------------------ finding 7: deeply nested JSON
_DEEP = "[" * 100_000 + "]" * 100_000


def _deep_dataset(tmp_path: Path, where: str) -> Path:
    root = tmp_path / "ds"
    if where == "episode metadata.json":
        _columnar(root, "arrow")
        (root / "data/1/metadata.json").write_text(_DEEP)
        return root
    _write(root, [_episode(3, 0)])
    meta_path = root / "data/metadata.json"
    if where == "metadata.json":
        meta_path.write_text(_DEEP)
    else:  # the serialized observation space, a JSON string inside the metadata
        meta = json.loads(meta_path.read_text())
        meta_path.write_text(json.dumps({**meta, "observation_space": _DEEP}))
    return root


@pytest.mark.parametrize("where", ["metadata.json", "observation_space", "episode metadata.json"])
def test_deeply_nested_json_in_minari_metadata_is_refused_by_name(tmp_path, where):
    """On d6e5639: a bare RecursionError from ``json.loads``."""
    root = _deep_dataset(tmp_path, where)
    with pytest.raises(ValueError, match="JSON nested too deeply to be read; refused"):
        _quiet_load(root)


def test_an_overwrite_of_a_folder_with_deeply_nested_metadata_is_refused_by_name(tmp_path):
    """``save_minari(..., overwrite=True)`` reads the metadata of what it would replace;
    on d6e5639 a RecursionError escaped its check."""
    root = _deep_dataset(tmp_path, "metadata.json")
    rows = _rows([5, 6])
    with pytest.raises(ValueError, match=r"is not a Minari dataset .*nested too deeply"):
        save_minari(rows, root, overwrite=True, **SPACES)
    assert (root / "data/metadata.json").read_text() == _DEEP
