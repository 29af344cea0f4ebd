"""No writer loses another's work (issue 26, items 5-7), with real processes.

* Several processes saving one new path: exactly one succeeds, the others are refused
  with a message, and the path holds the winner's rows whole (``DemonstrationBuffer.save``
  now; ``save_lerobot`` in ``tests/datasets/test_datasets_faults.py``).
* Two DAgger runs given one ``checkpoint_dir``: one runs, the other is refused.
* A full disk (a real 256 KiB tmpfs where the machine lets a test mount one, and an
  injected ``ENOSPC`` everywhere) names the destination and leaves what was there whole.
* Replacing a dataset or a checkpoint is one atomic exchange: a reader at any instant
  finds the old one or the new one, never none.
"""

from __future__ import annotations

import errno
import json
import multiprocessing
import os
import shutil
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest
import torch

from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.fs import DiskFullError, exclusive, publish
from tests._resume_run import run as dagger_run
from tests.data.test_checkpoint import demo_rows, same_buffer
from tests.datasets.test_datasets_faults import _rows, _same

FORK = multiprocessing.get_context("fork")


# ---------------------------------------------------- item 5: one winner per path
def _saver(index: int, path: str, barrier, results) -> None:
    buffer = DemonstrationBuffer()
    buffer.extend(demo_rows(20 + 10 * index, seed=index))
    barrier.wait()
    try:
        buffer.save(path)
        results.put((index, "ok"))
    except ValueError as err:
        results.put((index, f"ValueError: {err}"))
    except Exception as err:  # anything else fails the test
        results.put((index, f"{type(err).__name__}: {err}"))


@pytest.mark.parametrize("trial", range(3))
def test_four_processes_saving_one_path_one_wins_the_others_are_told(tmp_path, trial):
    path = tmp_path / "ckpt"
    barrier, results = FORK.Barrier(4), FORK.Queue()
    savers = [FORK.Process(target=_saver, args=(i, str(path), barrier, results)) for i in range(4)]
    for p in savers:
        p.start()
    outcome = dict(results.get(timeout=120) for _ in savers)
    for p in savers:
        p.join(timeout=60)
    won = [i for i, what in outcome.items() if what == "ok"]
    assert len(won) == 1, outcome
    for i, what in outcome.items():
        if i != won[0]:
            assert what.startswith("ValueError") and (
                "exists; pass overwrite=True" in what or "being written by another" in what
            ), what
    expected = DemonstrationBuffer()
    expected.extend(demo_rows(20 + 10 * won[0], seed=won[0]))
    assert same_buffer(DemonstrationBuffer.load(path)[0], expected)
    assert sorted(os.listdir(tmp_path)) == ["ckpt"]  # no lock, temporary or old copy left


def _dagger_runner(path: str, barrier, results) -> None:
    barrier.wait()
    try:
        result = dagger_run("frozenlake", path)
        results.put(("ok", len(result.buffer)))
    except ValueError as err:
        results.put((f"ValueError: {err}", None))


def test_two_dagger_runs_of_one_checkpoint_dir_one_runs_the_other_is_refused(tmp_path):
    path = tmp_path / "run"
    barrier, results = FORK.Barrier(2), FORK.Queue()
    runs = [FORK.Process(target=_dagger_runner, args=(str(path), barrier, results)) for _ in "ab"]
    for p in runs:
        p.start()
    outcome = [results.get(timeout=300) for _ in runs]
    for p in runs:
        p.join(timeout=60)
    assert sorted(what == "ok" for what, _ in outcome) == [False, True], outcome
    refusal = next(what for what, _ in outcome if what != "ok")
    assert "being used by a DAgger run" in refusal or "holds a saved DAgger run" in refusal
    rows = next(n for what, n in outcome if what == "ok")
    saved, state = DemonstrationBuffer.load(path)  # the winner's checkpoint, whole
    assert len(saved) == rows and state["next_round"] == 5


def _hold(path: str, held, release) -> None:
    with exclusive(path, what="used by a DAgger run"):
        held.set()
        release.wait(timeout=120)


def test_a_dagger_run_is_refused_while_another_process_holds_its_checkpoint_dir(tmp_path):
    path = tmp_path / "run"
    held, release = FORK.Event(), FORK.Event()
    holder = FORK.Process(target=_hold, args=(str(path), held, release))
    holder.start()
    try:
        assert held.wait(timeout=60)
        with pytest.raises(
            ValueError, match=r"being used by a DAgger run by another process \(pid"
        ):
            dagger_run("frozenlake", path)
        assert not path.exists()
    finally:
        release.set()
        holder.join(timeout=60)
    assert len(dagger_run("frozenlake", path).rounds) == 5  # free again


# ----------------------------------------------------------- item 6: a full disk
_FULL_DISK = r"""
import json, sys, warnings
sys.path[:0] = sys.argv[2:]
import torch
torch.set_num_threads(1)
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.fs import DiskFullError
from tests.data.test_checkpoint import demo_rows, same_buffer
from tests.datasets.test_datasets_faults import _rows, _same

disk = sys.argv[1]
out = {}
def attempt(name, fn, intact):
    try:
        fn()
        out[name] = "no error"
    except DiskFullError as err:
        out[name] = {"message": str(err), "errno": err.errno, "intact": intact()}
    except BaseException as err:
        out[name] = f"{type(err).__name__}: {err}"

small, big = _rows(0), _rows(1, lengths=(4000, 3000))
save_lerobot(small, disk + "/ds", fps=10)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    attempt("save_lerobot", lambda: save_lerobot(big, disk + "/ds", fps=10, overwrite=True),
            lambda: _same(load_lerobot(disk + "/ds").rows, small))
old = DemonstrationBuffer(); old.extend(demo_rows(10))
old.save(disk + "/ck")
new = DemonstrationBuffer(); new.extend(demo_rows(6000, seed=1))
attempt("buffer.save", lambda: new.save(disk + "/ck", overwrite=True),
        lambda: same_buffer(DemonstrationBuffer.load(disk + "/ck")[0], old))
grow = DemonstrationBuffer(path=disk + "/disk")
def extend_until_full():
    for i in range(1000):
        grow.extend(demo_rows(1000, first_episode=grow.next_episode, seed=i))
attempt("disk buffer extend", extend_until_full, lambda: len(grow) % 1000 == 0 and len(grow) > 0)
print(json.dumps(out))
"""


def _in_a_small_tmpfs(tmp_path: Path, script: str) -> dict:
    """Run ``script`` with a 256 KiB tmpfs mounted at its first argument, in a mount
    namespace of its own (as root, or as a user mapped to root); skip where neither is
    allowed."""
    disk = tmp_path / "disk"
    disk.mkdir()
    src = next(p for p in sys.path if (Path(p) / "imitrl").is_dir())
    root = str(Path(__file__).resolve().parents[2])
    inner = (
        f"mount -t tmpfs -o size=256k tmpfs {disk} && "
        f"{sys.executable} -c {_quote(script)} {disk} {src} {root}"
    )
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare(1) to mount a small file system")
    for flags in (["-m"], ["-rm"]):
        done = subprocess.run(
            [unshare, *flags, "sh", "-c", inner], capture_output=True, text=True, timeout=300
        )
        if done.returncode == 0 and done.stdout.strip():
            return json.loads(done.stdout.strip().splitlines()[-1])
        if "mount" not in done.stderr and "unshare" not in done.stderr:
            raise AssertionError(done.stderr[-3000:])
    pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()[-300:]}")


def _quote(text: str) -> str:
    import shlex

    return shlex.quote(textwrap.dedent(text))


def test_a_full_disk_names_the_destination_and_keeps_what_was_there(tmp_path):
    out = _in_a_small_tmpfs(tmp_path, _FULL_DISK)
    disk = tmp_path / "disk"
    for name, where in (
        ("save_lerobot", "ds"),
        ("buffer.save", "ck"),
        ("disk buffer extend", "disk"),
    ):
        got = out[name]
        assert isinstance(got, dict), (name, got)
        assert got["errno"] == errno.ENOSPC and got["intact"], (name, got)
        assert f"to {disk / where} (" in got["message"], got["message"]
        assert "no space left on the device" in got["message"]


def test_an_injected_enospc_names_the_destination(tmp_path, monkeypatch):
    """Where no small file system can be mounted: ENOSPC at each writer's own write."""
    from imitrl.data import checkpoint
    from imitrl.data import disk as disk_module

    old = DemonstrationBuffer()
    old.extend(demo_rows(10))
    old.save(tmp_path / "ck")

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoint, "_write_file", full)
    with pytest.raises(DiskFullError, match=f"to {tmp_path / 'ck'} .*nothing was published"):
        old.save(tmp_path / "ck", overwrite=True)
    monkeypatch.undo()
    assert same_buffer(DemonstrationBuffer.load(tmp_path / "ck")[0], old)
    grow = DemonstrationBuffer(path=tmp_path / "disk")
    grow.extend(demo_rows(10))
    monkeypatch.setattr(disk_module.os, "posix_fallocate", full)
    with pytest.raises(DiskFullError, match=f"to {tmp_path / 'disk'} .*keeps its 10 rows"):
        grow.extend(demo_rows(10, first_episode=2))
    assert len(grow) == 10


# ---------------------------------------------------- item 7: one atomic exchange
def test_every_instant_of_a_replacement_holds_a_whole_dataset(tmp_path, monkeypatch):
    """Each step of the swap is observed as it happens: the path names a whole dataset
    before and after every rename or exchange (two renames would leave none between)."""
    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    seen = []

    def observe(step):
        def wrapped(*args):
            out = step(*args)
            seen.append((path / "meta" / "info.json").is_file())
            return out

        return wrapped

    monkeypatch.setattr(publish, "exchange", observe(publish.exchange))
    monkeypatch.setattr(publish.os, "rename", observe(os.rename))
    save_lerobot(_rows(1), path, fps=10, overwrite=True)
    monkeypatch.undo()
    assert seen and all(seen), seen
    assert _same(load_lerobot(path).rows, _rows(1))


def _reader(path: str, stop, results) -> None:
    misses = reads = 0
    while not stop.is_set():
        reads += 1
        misses += not os.path.isfile(os.path.join(path, "meta", "info.json"))
    results.put((reads, misses))


def test_a_reader_process_never_finds_the_dataset_missing_while_it_is_replaced(tmp_path):
    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    stop, results = FORK.Event(), FORK.Queue()
    reader = FORK.Process(target=_reader, args=(str(path), stop, results))
    reader.start()
    try:  # 15 replacements: the reader spins a core throughout (the test above checks
        # each exchange's moment; this one that no reader in another process sees a gap)
        for i in range(15):
            save_lerobot(_rows(i % 3), path, fps=10, overwrite=True)
    finally:
        stop.set()
    reads, misses = results.get(timeout=60)
    reader.join(timeout=60)
    assert reads > 100 and misses == 0, (reads, misses)


def test_a_checkpoint_replacement_is_one_exchange_too(tmp_path, monkeypatch):
    old, new = DemonstrationBuffer(), DemonstrationBuffer()
    old.extend(demo_rows(10))
    new.extend(demo_rows(30, seed=3))
    path = old.save(tmp_path / "ck")
    seen = []
    real = publish.exchange

    def exchange(a, b):
        ok = real(a, b)
        seen.append((path / "manifest.json").is_file())
        return ok

    monkeypatch.setattr(publish, "exchange", exchange)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new.save(path, overwrite=True)
    assert seen == [True]
    assert same_buffer(DemonstrationBuffer.load(path)[0], new)
    assert torch.equal(
        DemonstrationBuffer.load(path)[0].data["observation"], new.data["observation"]
    )
