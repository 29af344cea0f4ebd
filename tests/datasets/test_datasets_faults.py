"""Faults at the dataset writer (issue 13): a write lands whole or leaves what was there
untouched, under any exception or kill; of two writers to one path at most one succeeds;
``overwrite=True`` replaces only a dataset, never the working directory or someone's folder.
Reader faults: ``tests/datasets/test_datasets_faults_read.py``.

Every test here is a row of the fault table: the case, and what happens now.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import warnings
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.datasets import load_lerobot, save_lerobot
from tests import _child


# ----------------------------------------------------------------- helpers
def _rows(seed: int, lengths=(3, 2)) -> TensorDict:
    """Small rows save_lerobot writes; different seeds give different values."""
    g = torch.Generator().manual_seed(seed)
    parts = []
    for e, n in enumerate(lengths):
        done = torch.arange(n).eq(n - 1).unsqueeze(-1)
        label = torch.randint(0, 2, (n,), generator=g)
        parts.append(
            TensorDict(
                {
                    keys.OBSERVATION: torch.randn(n, 4, generator=g),
                    keys.EXPERT_ACTION: label,
                    keys.ACTION: label.clone(),
                    keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
                    keys.EPISODE: torch.full((n,), e),
                    keys.ROUND: torch.zeros(n, dtype=torch.int64),
                    keys.STEP: torch.arange(n),
                    (keys.NEXT, keys.REWARD): torch.ones(n, 1),
                    (keys.NEXT, keys.DONE): done,
                },
                batch_size=[n],
            )
        )
    return torch.cat(parts)


def _load(path, **kwargs) -> TensorDict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(path, **kwargs).rows


def _same(a: TensorDict, b: TensorDict) -> bool:
    return set(a.keys(True, True)) == set(b.keys(True, True)) and all(
        a.get(k).dtype == b.get(k).dtype and torch.equal(a.get(k), b.get(k))
        for k in a.keys(True, True)
    )


def _leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if ".imitrl-" in p.name)


# ------------------------------------------------------- two writers at once
def _writer(index: int, barrier, paths: list[str], results) -> None:
    """One of two processes: for each path, wait for the other, then write it at once."""
    torch.set_num_threads(1)
    rows = _rows(index)
    for path in paths:
        barrier.wait()
        try:
            save_lerobot(rows, path, fps=10)
            results.put((path, index, "ok"))
        except ValueError as err:
            results.put((path, index, f"ValueError: {err}"))
        except Exception as err:  # anything else fails the test below
            results.put((path, index, f"{type(err).__name__}: {err}"))


def test_two_writers_at_once_one_wins_every_time(tmp_path):
    """30 trials of two processes saving to one path at the same moment: exactly one
    succeeds, the other gets a ValueError, and the path holds the winner's rows whole."""
    trials = [str(tmp_path / f"ds{i}") for i in range(30)]
    # forks of the tests' preloaded server, never of this process (it holds torch threads)
    ctx = _child.context()
    barrier, results = ctx.Barrier(2), ctx.Queue()
    workers = [ctx.Process(target=_writer, args=(i, barrier, trials, results)) for i in (0, 1)]
    for w in workers:
        w.start()
    outcome: dict[str, dict[int, str]] = {}
    for _ in range(2 * len(trials)):
        path, index, what = results.get(timeout=120)
        outcome.setdefault(path, {})[index] = what
    for w in workers:
        w.join(timeout=60)
    expected = [_rows(0), _rows(1)]
    for path in trials:
        won = [i for i, what in outcome[path].items() if what == "ok"]
        lost = [what for what in outcome[path].values() if what != "ok"]
        assert len(won) == 1, (path, outcome[path])
        assert lost[0].startswith("ValueError") and (
            "exists" in lost[0] or "being written" in lost[0]
        ), lost[0]
        assert _same(_load(path), expected[won[0]]), path
    assert _leftovers(tmp_path) == []


# --------------------------------------------------------- overwrite=True
def test_overwrite_never_takes_the_working_directory(tmp_path, monkeypatch):
    (tmp_path / "notes.txt").write_text("a user's file")
    monkeypatch.chdir(tmp_path)
    for path in (".", tmp_path, tmp_path.parent, "sub/.."):
        with pytest.raises(ValueError, match="working directory"):
            save_lerobot(_rows(0), path, fps=10, overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "a user's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def _user_folder(root: Path) -> None:
    root.mkdir()
    (root / "thesis.tex").write_text("...")


def _dataset_and_more(root: Path) -> None:
    save_lerobot(_rows(5), root, fps=10)
    (root / "notes.txt").write_text("mine")


def _bare_info(root: Path) -> None:
    (root / "meta").mkdir(parents=True)
    (root / "meta/info.json").write_text(json.dumps({"fps": 10}))  # no codebase_version


def _a_file(root: Path) -> None:
    root.write_text("not a directory")


def _a_link(root: Path) -> None:
    save_lerobot(_rows(5), root.parent / "real", fps=10)
    root.symlink_to(root.parent / "real")


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (_user_folder, "not a LeRobot dataset"),
        (_dataset_and_more, r"holds \['notes.txt'\] beside the dataset"),
        (_bare_info, "not a LeRobot dataset"),
        (_a_file, "not a directory"),
        (_a_link, "symbolic link"),
    ],
)
def test_overwrite_replaces_only_a_dataset(tmp_path, make, message):
    target = tmp_path / "target"
    make(target)
    before = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    with pytest.raises(ValueError, match=message):
        save_lerobot(_rows(0), target, fps=10, overwrite=True)
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == before


def test_overwrite_replaces_a_dataset_whole(tmp_path):
    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    (path / "README.md").write_text("hub card")  # what a hub download holds is allowed
    save_lerobot(_rows(1), path, fps=10, overwrite=True)
    assert _same(_load(path), _rows(1)) and not (path / "README.md").exists()
    assert _leftovers(tmp_path) == []


def test_an_error_while_writing_leaves_the_old_dataset(tmp_path, monkeypatch):
    from imitrl.datasets.lerobot import _v3_files

    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(_v3_files, "_write_stats", boom)
    with pytest.raises(OSError, match="disk full"):
        save_lerobot(_rows(1), path, fps=10, overwrite=True)
    assert _same(_load(path), _rows(0)) and _leftovers(tmp_path) == []
    with pytest.raises(OSError, match="disk full"):
        save_lerobot(_rows(1), tmp_path / "new", fps=10)
    assert not (tmp_path / "new").exists() and _leftovers(tmp_path) == []


def test_a_failed_swap_puts_the_old_dataset_back(tmp_path, monkeypatch):
    """Where the atomic exchange is missing (two renames), a failing second rename puts
    the old dataset back."""
    from imitrl.fs import publish

    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    real, calls = os.rename, []

    def second_rename_fails(src, dst):
        calls.append(dst)
        if len(calls) == 2:  # the new dataset into place, after the old one moved aside
            raise OSError("rename refused")
        real(src, dst)

    monkeypatch.setattr(publish, "exchange", lambda a, b: False)
    monkeypatch.setattr(publish.os, "rename", second_rename_fails)
    with pytest.raises(OSError, match="rename refused"):
        save_lerobot(_rows(1), path, fps=10, overwrite=True)
    monkeypatch.undo()
    assert _same(_load(path), _rows(0)) and _leftovers(tmp_path) == []


def test_a_second_writer_is_refused_while_the_first_holds_the_path(tmp_path):
    fcntl = pytest.importorskip("fcntl")
    lock = tmp_path / ".ds.imitrl-lock"
    fd = os.open(lock, os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.write(fd, b"pid 12345")
    try:
        with pytest.raises(ValueError, match=r"being written by another process \(pid 12345"):
            save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    finally:
        os.close(fd)
    assert not (tmp_path / "ds").exists()
    save_lerobot(_rows(0), tmp_path / "ds", fps=10)  # a lock nobody holds is taken over
    assert _leftovers(tmp_path) == []


# ------------------------------------------------------------- kill points
def _kill_at(point: str, path: str) -> None:
    """In a child process: overwrite ``path``, SIGKILL-like exit (no cleanup) at ``point``."""
    import imitrl.fs.publish as publish
    from imitrl.datasets.lerobot import _v3_files

    def die(*args, **kwargs):
        os._exit(9)

    real_exchange, real_rename, renames = publish.exchange, os.rename, []

    def exchange_then_die(a, b):
        assert real_exchange(a, b)
        os._exit(9)

    def rename(src, dst):
        real_rename(src, dst)
        renames.append(dst)
        if len(renames) == {"old moved aside": 1, "new moved in": 2}.get(point):
            os._exit(9)

    def rmtree_partly(tree, *args, **kwargs):
        first = sorted(Path(tree).rglob("*.parquet"))[0]
        first.unlink()
        os._exit(9)

    patches = {
        "mid write": [(_v3_files, "_write_stats", die)],
        "written, not moved": [(publish, "swap_in", die)],
        "exchanged, old not removed": [(publish, "exchange", exchange_then_die)],
        "old half removed": [(publish, "remove_tree", rmtree_partly)],
        # where renameat2 is missing: two renames
        "old moved aside": [
            (publish, "exchange", lambda a, b: False),
            (publish.os, "rename", rename),
        ],
        "new moved in": [(publish, "exchange", lambda a, b: False), (publish.os, "rename", rename)],
    }
    for module, name, fn in patches[point]:
        setattr(module, name, fn)
    save_lerobot(_rows(1), path, fps=10, overwrite=True)
    os._exit(0)


KILL_POINTS = [
    "mid write",
    "written, not moved",
    "exchanged, old not removed",
    "old moved aside",
    "new moved in",
]
NEW_IN_PLACE = ("exchanged, old not removed", "new moved in", "old half removed")


@pytest.mark.parametrize("point", [*KILL_POINTS, "old half removed"])
def test_a_killed_writer_leaves_a_whole_dataset_and_the_next_call_sorts_it_out(tmp_path, point):
    path = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    child = multiprocessing.get_context("fork").Process(target=_kill_at, args=(point, str(path)))
    child.start()
    child.join(timeout=60)
    assert child.exitcode == 9
    assert _leftovers(tmp_path)  # the kill left something behind
    if point == "old moved aside":  # the reader names where the previous dataset is
        with pytest.raises(ValueError, match=r"killed save_lerobot left the previous one"):
            load_lerobot(path)
    else:  # a reader at this instant finds a whole dataset, old or new
        assert _same(_load(path), _rows(1) if point in NEW_IN_PLACE else _rows(0))
    with pytest.warns(UserWarning, match="killed writer's leftovers"):
        with pytest.raises(ValueError, match="exists"):
            save_lerobot(_rows(2), path, fps=10)  # recovers first, then refuses to overwrite
    assert _same(_load(path), _rows(1) if point in NEW_IN_PLACE else _rows(0))
    assert _leftovers(tmp_path) == []


def test_a_write_killed_before_the_rename_leaves_no_dataset(tmp_path):
    target = tmp_path / "fresh"
    child = multiprocessing.get_context("fork").Process(
        target=_kill_at, args=("written, not moved", str(target))
    )
    child.start()
    child.join(timeout=60)
    assert child.exitcode == 9 and not target.exists() and _leftovers(tmp_path)
    with pytest.warns(UserWarning, match=r"removed \.fresh\.imitrl-tmp-\w+ \(an unfinished write"):
        save_lerobot(_rows(2), target, fps=10)
    assert _same(_load(target), _rows(2)) and _leftovers(tmp_path) == []
