"""Hostile file systems, second round (issue 42, findings 1, 2 and 7's file-system items).

* A symbolic link (or a hard link) planted where imitrl keeps a lock, a staging folder or
  ``eval.json`` never makes it write outside: every writer refuses it, naming it, and the
  file it points to is untouched (real ``imitrl bc`` processes, and every library writer).
* ``--out X --overwrite`` killed at any instant leaves the previous run in ``X`` whole; a
  killed or failed run never blocks its own rerun.
* A full disk or a read-only folder under ``--out``: one line, exit 1, ``X`` as it was
  (a real tmpfs in a mount namespace of the test's own).
* Published folders take the user's umask; a path too long for the system is one line.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest

from imitrl.cli import main
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import save_lerobot, save_minari
from imitrl.fs import PlantedLinkError
from imitrl.fs.run_folder import staging_folder
from tests import _child
from tests._resume_run import run as dagger_run
from tests.data.test_checkpoint import demo_rows
from tests.datasets.minari.test_write import _play
from tests.datasets.test_datasets_faults import _rows

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--env", "CartPole-v1", "--demos", "1", "--steps", "2", "--batch-size", "8",
        "--hidden", "8", "--eval-episodes", "1", "--max-episode-steps", "10", "--no-progress"]  # fmt: skip
SECRET = b"ssh-ed25519 AAAA precious key\n"


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with (
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore")
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


def cli(*argv: str, cwd: Path | None = None, **kwargs) -> subprocess.CompletedProcess:
    """``python -m imitrl ARGV`` in a process of its own (this checkout's package)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT / "src")}
    return _child.run(
        [sys.executable, "-m", "imitrl", *argv],
        cwd=cwd or ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        **kwargs,
    )


# --------------------------------------------- finding 1: a planted link at the lock
def _plant(kind: str, at: Path, victim: Path) -> None:
    """A link at ``at`` to ``victim`` (outside): a symbolic link to a file, a dangling one
    (the file it names does not exist yet), or a hard link to the file itself."""
    at.parent.mkdir(parents=True, exist_ok=True)
    if kind == "dangling":
        victim.unlink()
        os.symlink(victim, at)
    elif kind == "hard":
        os.link(victim, at)
    else:
        os.symlink(victim, at)


def _writers() -> dict:
    return {
        "save_lerobot": lambda p: save_lerobot(_rows(0), p, fps=10),
        "save_minari": lambda p: save_minari(
            _play("CartPole-v1", [3], seed=0), p, env_id="CartPole-v1"
        ),
        "buffer.save": lambda p: _buffer().save(p),
        "dagger checkpoint_dir": lambda p: dagger_run("frozenlake", p),
    }


def _buffer() -> DemonstrationBuffer:
    buffer = DemonstrationBuffer()
    buffer.extend(demo_rows(10))
    return buffer


@pytest.mark.parametrize("kind", ["symbolic", "dangling", "hard"])
@pytest.mark.parametrize(
    "writer", ["save_lerobot", "save_minari", "buffer.save", "dagger checkpoint_dir"]
)
def test_a_link_planted_at_a_writers_lock_is_refused_and_its_target_untouched(
    tmp_path, writer, kind
):
    victim = tmp_path / "home" / "authorized_keys"
    victim.parent.mkdir()
    victim.write_bytes(SECRET)
    dest = tmp_path / "results" / "out"
    lock = dest.parent / f".{dest.name}.imitrl-lock"
    _plant(kind, lock, victim)
    with pytest.raises(PlantedLinkError, match=r"\.out\.imitrl-lock"):
        _writers()[writer](dest)
    if kind == "dangling":
        assert not victim.exists(), "the lock created a file outside the folder"
    else:
        assert victim.read_bytes() == SECRET
    assert os.path.lexists(lock), "the planted link is left for the user to see"
    assert not dest.exists()


@pytest.mark.parametrize("kind", ["symbolic", "dangling", "hard"])
def test_imitrl_bc_refuses_a_link_planted_at_its_lock(tmp_path, kind):
    """A cloned repository commits ``results/.bc.imitrl-lock -> ~/.ssh/authorized_keys``;
    a plain ``imitrl bc`` (its default ``--out results/bc``) run there, as a process."""
    victim = tmp_path / "home" / "authorized_keys"
    victim.parent.mkdir()
    victim.write_bytes(SECRET)
    repo = tmp_path / "repo"
    _plant(kind, repo / "results" / ".bc.imitrl-lock", victim)
    done = cli("bc", *TINY, cwd=repo)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr, done.stderr
    assert ".bc.imitrl-lock" in done.stderr
    if kind == "dangling":
        assert not victim.exists()
    else:
        assert victim.read_bytes() == SECRET
    assert not (repo / "results" / "bc").exists()


def test_a_link_planted_at_the_staging_folder_or_eval_json_is_never_written_through(
    tmp_path,
):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = tmp_path / "results" / "bc"
    out.parent.mkdir()
    os.symlink(elsewhere, staging_folder(out))
    status, _, err = run(["bc", *TINY, "--out", str(out)])
    assert status == 2 and ".bc.imitrl-run" in err and "symbolic link" in err, err
    assert list(elsewhere.iterdir()) == [] and not out.exists()
    victim = tmp_path / "victim"
    victim.write_bytes(SECRET)
    folder = tmp_path / "eval"
    folder.mkdir()
    os.symlink(victim, folder / "eval.json")
    status, _, err = run(["eval", "--expert", "cartpole", "--env", "CartPole-v1",
                          "--eval-episodes", "1", "--max-episode-steps", "5", "--no-progress",
                          "--out", str(folder), "--overwrite"])  # fmt: skip
    assert status == 0, err
    assert victim.read_bytes() == SECRET
    assert not (folder / "eval.json").is_symlink()
    assert json.loads((folder / "eval.json").read_text())["env"] == "CartPole-v1"


# --------------------------------- finding 2: a killed --overwrite loses nothing
def _snapshot(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("delay", [0.0, 0.4, 1.5])
def test_a_killed_overwrite_leaves_the_previous_run_whole(tmp_path, delay):
    out = tmp_path / "run"
    assert run(["bc", *TINY, "--out", str(out)])[0] == 0
    before = _snapshot(out)
    assert {"results.json", "learner.pt", "config.json", "curves.png"} <= set(before)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT / "src")}
    long = [a if a != "2" else "100000" for a in TINY]  # --steps 100000: still fitting
    proc = _child.Popen(
        [sys.executable, "-m", "imitrl", "bc", *long, "--out", str(out), "--overwrite"],
        cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        started = staging_folder(out).exists() or not (out / "results.json").exists()
        if started:
            break
        time.sleep(0.02)
    time.sleep(delay)
    assert proc.poll() is None, "the new run ended before the kill"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert _snapshot(out) == before, "the previous run changed"
    # the finished run is still protected; the killed one's leftovers never block
    status, _, err = run(["bc", *TINY, "--out", str(out)])
    assert status == 2 and "holds a previous run" in err, err
    status, _, err = run(["bc", *TINY, "--out", str(out), "--overwrite", "--seed", "3"])
    assert status == 0, err
    assert not staging_folder(out).exists()
    assert json.loads((out / "config.json").read_text())["config"]["seed"] == 3


def test_a_failed_or_killed_run_never_blocks_its_rerun(tmp_path):
    out = tmp_path / "results" / "bc"
    status, _, err = run(["bc", *TINY, "--out", str(out), "--dataset", str(tmp_path / "no")])
    assert status == 2, err
    status, _, err = run(["bc", *TINY, "--out", str(out)])  # corrected: no --overwrite
    assert status == 0, err
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT / "src")}
    fresh = tmp_path / "fresh"
    long = [a if a != "2" else "100000" for a in TINY]
    proc = _child.Popen(
        [sys.executable, "-m", "imitrl", "bc", *long, "--out", str(fresh)],
        cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while not (staging_folder(fresh) / "logs").exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not fresh.exists() or not any(fresh.iterdir())
    status, _, err = run(["bc", *TINY, "--out", str(fresh)])
    assert status == 0, err
    assert (fresh / "results.json").is_file() and not staging_folder(fresh).exists()


# ------------------------------------------- finding 7: permissions, long paths
@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_published_folders_take_the_users_umask(tmp_path, umask):
    expected = 0o777 & ~umask
    old = os.umask(umask)
    try:
        paths = [save_lerobot(_rows(0), tmp_path / "ds", fps=10)]
        _buffer().save(tmp_path / "ck")
        paths.append(tmp_path / "ck")
        assert run(["bc", *TINY, "--out", str(tmp_path / "bc")])[0] == 0
        paths.append(tmp_path / "bc")
    finally:
        os.umask(old)
    for path in paths:
        assert path.stat().st_mode & 0o777 == expected, (path, oct(path.stat().st_mode))
        for inner in path.rglob("*"):
            if inner.is_dir():
                assert inner.stat().st_mode & 0o777 == expected, inner


def test_a_path_deeper_than_the_system_allows_is_one_line_and_a_deep_one_works(tmp_path):
    deep = Path(*["a"] * 1500)
    try:
        done = cli("bc", *TINY, "--out", str(deep), cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-2000:]
        assert (tmp_path / deep / "results.json").is_file()
    finally:  # rm(1) walks it without recursion (shutil.rmtree, as pytest uses, cannot)
        subprocess.run(["rm", "-rf", str(tmp_path / "a")], check=True)
    for out in (Path(*["b"] * 3000), Path("c" * 300)):
        status, _, err = run(["bc", *TINY, "--out", str(tmp_path / out)])
        assert status == 2 and err.count("\n") == 1, err[-500:]
        assert "choose a shorter one" in err


# -------------------------------- a full disk and a read-only folder under --out
_SMALL_DISK = r"""
import contextlib, io, json, os, sys, warnings
sys.path[:0] = [sys.argv[2]]
from imitrl.cli import main
from imitrl.datasets import save_lerobot
from imitrl.fs import NotWritableError
from tests.datasets.test_datasets_faults import _rows
disk, tiny = sys.argv[1], json.loads(sys.argv[3])
result = {}
def cli(*argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        status = main(list(argv))
    return status, err.getvalue()
assert cli("bc", *tiny, "--out", disk + "/prev")[0] == 0
snapshot = lambda d: {f: open(os.path.join(d, f), "rb").read() for f in sorted(os.listdir(d))
                      if os.path.isfile(os.path.join(d, f))}
before = snapshot(disk + "/prev")
free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
with open(disk + "/filler", "wb") as f:  # leave ~8 KiB: less than a run's files
    f.write(b"x" * max(0, free - 8192))
result["full"] = cli("bc", *tiny, "--out", disk + "/new")
result["full_overwrite"] = cli("bc", *tiny, "--out", disk + "/prev", "--overwrite")
result["prev_intact"] = snapshot(disk + "/prev") == before
result["leftovers"] = sorted(n for n in os.listdir(disk) if n.startswith("."))
read_only = sys.argv[4]  # a second tmpfs, mounted read-only
result["read_only"] = cli("bc", *tiny, "--out", read_only + "/bc")
try:
    save_lerobot(_rows(0), read_only + "/ds", fps=10)
    result["save_lerobot"] = "no error"
except NotWritableError as err:
    result["save_lerobot"] = str(err)
print(json.dumps(result))
"""


def test_a_full_disk_or_a_read_only_folder_under_out_is_one_line(tmp_path):
    disk, read_only = tmp_path / "disk", tmp_path / "read_only"
    disk.mkdir()
    read_only.mkdir()
    script = textwrap.dedent(_SMALL_DISK)
    inner = (
        f"mount -t tmpfs -o size=512k tmpfs {disk} && "
        f"mount -t tmpfs -o size=64k tmpfs {read_only} && "
        f"mount -o remount,ro {read_only} && "
        f"{sys.executable} -c \"$0\" {disk} {ROOT} '{json.dumps(TINY)}' {read_only}"
    )
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare(1) to mount a small file system")
    done = subprocess.run(
        [unshare, "-m", "sh", "-c", inner, script],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    if done.returncode != 0 and "mount" in done.stderr[-300:]:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr[-300:]}")
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    for case in ("full", "full_overwrite"):
        status, err = got[case]
        assert status == 1 and err.count("\n") == 1, (case, err)
        assert "no space left on the device" in err and "Traceback" not in err, err
    assert got["prev_intact"], "the previous run changed"
    assert got["leftovers"] == [], got["leftovers"]  # no staging folder left behind
    status, err = got["read_only"]
    assert status == 1 and err.count("\n") == 1 and "read-only file system" in err, err
    assert "read-only file system" in got["save_lerobot"], got["save_lerobot"]


# ------------------------------------- the outside review of the first fixes (round 2)
DAGGER = ["dagger", *TINY, "--episodes-per-round", "1"]


@pytest.mark.parametrize("where", ["finished", "unfinished"])
def test_resume_never_writes_through_a_link_planted_in_the_run(tmp_path, where):
    """A finished run whose files are links out (copied for --resume), or a staging folder
    a repository committed with links in it (continued as it is): refused, naming the
    link; the files the links point to untouched."""
    out = tmp_path / "d"
    assert run([*DAGGER, "--rounds", "2", "--out", str(out)])[0] == 0
    victim = tmp_path / "victim"
    victim.write_bytes(SECRET)
    folder = out
    if where == "unfinished":
        folder = staging_folder(out)
        shutil.copytree(out, folder)
        shutil.rmtree(out)
        (folder / "results.json").unlink()
    (folder / "config.json").unlink()
    os.symlink(victim, folder / "config.json")
    status, _, err = run([*DAGGER, "--rounds", "3", "--out", str(out), "--resume"])
    assert status == 2 and "config.json" in err and "symbolic link" in err, err
    assert victim.read_bytes() == SECRET
    os.unlink(folder / "config.json")
    os.mkfifo(folder / "config.json")  # a FIFO is refused the same way (was shutil.Error)
    status, _, err = run([*DAGGER, "--rounds", "3", "--out", str(out), "--resume"])
    assert status == 2 and err.count("\n") == 1 and "special file" in err, err


@pytest.mark.parametrize(
    "files", [{"config.json": "{}", "logs/notes.txt": "mine"}, {"eval.json": "{}"}]
)
def test_a_folder_without_a_finished_run_is_never_replaced(tmp_path, files):
    out = tmp_path / "proj"
    for name, text in files.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)
    for extra in ([], ["--overwrite"]):
        status, _, err = run(["bc", *TINY, "--out", str(out), *extra])
        assert status == 2 and "never deletes them" in err, err
    assert {str(p.relative_to(out)): p.read_text() for p in out.rglob("*") if p.is_file()} == files


def test_an_older_killed_dagger_run_in_out_is_continued_by_resume_not_discarded(tmp_path):
    """A DAgger checkpoint ``run/`` left in --out itself (an older imitrl wrote there
    directly) is refused without --resume and continued by it from its last round."""
    out = tmp_path / "x"
    assert run([*DAGGER, "--rounds", "2", "--out", str(out)])[0] == 0
    for name in ("results.json", "curves.png", "learner.pt", "config.json"):
        (out / name).unlink()  # what a killed run of the older layout left
    status, _, err = run([*DAGGER, "--rounds", "3", "--out", str(out)])
    assert status == 2, err
    status, _, err = run([*DAGGER, "--rounds", "3", "--out", str(out), "--resume"])
    assert status == 0, err
    rounds = json.loads((out / "results.json").read_text())["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2]
    whole = tmp_path / "whole"
    assert run([*DAGGER, "--rounds", "3", "--out", str(whole)])[0] == 0
    assert rounds == json.loads((whole / "results.json").read_text())["rounds"]


def test_a_replaced_run_a_kill_left_at_the_staging_name_is_never_resumed(tmp_path, monkeypatch):
    """Killed right after the exchange: the replaced (older) run lies at the staging
    name. The next --resume removes it and continues the newer run in --out."""
    from imitrl.fs import run_folder as output

    out = tmp_path / "x"
    assert run([*DAGGER, "--rounds", "2", "--out", str(out)])[0] == 0
    older = tmp_path / "older"
    shutil.copytree(out, older)

    def killed(stage: Path, target: Path) -> None:  # exchanged, then the process "dies"
        output.swap_in(stage, target)
        raise KeyboardInterrupt

    monkeypatch.setattr(output, "_publish", killed)
    assert run([*DAGGER, "--rounds", "3", "--out", str(out), "--resume"])[0] == 130
    monkeypatch.undo()
    assert (staging_folder(out) / "results.json").is_file()  # the older run, 2 rounds
    status, _, err = run([*DAGGER, "--rounds", "4", "--out", str(out), "--resume"])
    assert status == 0, err
    rows = [r["rows_trained"] for r in json.loads((out / "results.json").read_text())["rounds"]]
    whole = tmp_path / "whole"
    assert run([*DAGGER, "--rounds", "4", "--out", str(whole)])[0] == 0
    expected = json.loads((whole / "results.json").read_text())["rounds"]
    assert rows == [r["rows_trained"] for r in expected]
    assert not staging_folder(out).exists()


def test_planted_leftovers_deep_folders_and_odd_out_paths_are_one_line(tmp_path):
    from imitrl.fs.contained import links_stay_inside

    out = tmp_path / "out"
    out.parent.mkdir(exist_ok=True)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep").write_text("kept")
    os.symlink(victim, tmp_path / ".out.imitrl-tmp-abc")  # a link at a leftover's name
    status, _, err = run(["bc", *TINY, "--out", str(out)])
    assert status == 2 and err.count("\n") == 1 and ".out.imitrl-tmp-abc" in err, err
    assert (victim / "keep").read_text() == "kept"
    deep = tmp_path / "ds"
    try:
        subprocess.run(["mkdir", "-p", str(deep / Path(*["d"] * 1500))], check=True)
        links_stay_inside(deep)  # no RecursionError: the walk is a loop
    finally:
        subprocess.run(["rm", "-rf", str(deep)], check=True)
    (tmp_path / "afile").write_text("x")
    os.mkfifo(tmp_path / "fifo")
    for bad in (tmp_path / "afile" / "x", tmp_path / "fifo" / "x", Path("/proc/1/x")):
        status, _, err = run(["bc", *TINY, "--out", str(bad)])
        assert status == 2 and err.count("\n") == 1 and "Traceback" not in err, (bad, err)
