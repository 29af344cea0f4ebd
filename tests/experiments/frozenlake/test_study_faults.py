"""`imitrl frozenlake` under bad input and interruption: nothing lost, nothing silently wrong.

Every bad flag is refused before any work (exit 2, one line on stderr, nothing at
--out); a goal that cannot be reached scores 0 and still draws its figures; an
exception, Ctrl-C or SIGKILL mid-run leaves the previous results at --out whole.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import imitrl
from imitrl.cli import main
from imitrl.evaluation.evaluate import wilson_interval
from imitrl.experiments.frozenlake import figures, figures_irl, outputs, study
from imitrl.tabular import TabularMDP
from tests import _child

UNREACHABLE = "SFFF,FFFF,FFHH,FFHG"  # the goal is walled off by holes
SRC = str(Path(imitrl.__file__).resolve().parents[1])

# (flags, what the one line on stderr says)
BAD_FLAGS = [
    (["--map-name", "5x5"], "'5x5' is not a gymnasium FrozenLake map: one of 4x4, 8x8"),
    (["--desc", "SFFF,FHF,FFFH,HFFG"], "rows must all have the same length"),
    (["--desc", "FFFF,FHFH,FFFH,HFFG"], "exactly one start S, got 0"),
    (["--desc", "SFFS,FHFH,FFFH,HFFG"], "exactly one start S, got 2"),
    (["--desc", "SFFF,FHFH,FFFH,HFFF"], "no goal G"),
    (["--desc", "SFFF,FXFH,FFFH,HFFG"], "letters must be S (start), F (frozen)"),
    (["--desc", "sfff,fhfh,fffh,hffg"], "letters must be"),
    (["--desc", ","], "--desc needs non-empty rows"),
    (["--desc", "SFFF,,HFFG"], "--desc needs non-empty rows"),
    (["--desc", "S,F,G"], "--desc needs at least 2 columns"),
    (["--max-steps", "10"], "--tv-steps [20] past the time limit of 10 steps"),
    (["--gamma", "0"], "--gamma must be in (0, 1], got 0.0"),
    (["--gamma", "1.5"], "--gamma must be in (0, 1]"),
    (["--gamma", "nan"], "--gamma must be in (0, 1]"),
    (["--lr", "0"], "--lr must be > 0"),
    (["--ex-corruption", "1.5"], "--ex-corruption must be in [0, 1]"),
    (["--sweep-sizes", "0,3"], "--sweep-sizes must be an integer >= 1, got 0 in [0, 3]"),
    (["--sweep-sizes", "3,3"], "--sweep-sizes: each value once"),
    (["--ex-demo-counts", "5,-20"], "--ex-demo-counts must be an integer >= 1"),
    (["--tv-steps", "0,5"], "--tv-steps must be an integer >= 1"),
    (["--tv-steps", ""], "--tv-steps: give at least one step"),
    (["--chain-panels", "0:10"], "--chain-panels must be eps:T with eps in (0, 1]"),
    (["--chain-panels", "0.1:0"], "--chain-panels must be an integer >= 1"),
    (["--probe-states", "16"], "--probe-states [16] outside the 16 states"),
    (["--probe-states", "-1"], "--probe-states must be an integer >= 0"),
    (["--max-steps", "0"], "--max-steps must be an integer >= 1"),
    (["--demo-seed", "-1"], "--demo-seed must be an integer >= 0"),
    (["--ex-seed", "-5"], "--ex-seed must be an integer >= 0"),
    (["--eval-scale", "5"], "--eval-scale 5 applies to --protocol batched only"),
    *(
        ([flag, value], f"{flag} must be an integer >= 1")
        for flag, value in [
            ("--eval-scale", "0"),
            ("--vi-iters", "0"),
            ("--demo-episodes", "0"),
            ("--fit-steps", "0"),
            ("--eval-episodes", "-3"),
            ("--sweep-datasets", "0"),
            ("--sweep-fit-steps", "0"),
            ("--sweep-eval-episodes", "0"),
            ("--chain-samples", "0"),
            ("--dagger-rounds", "0"),
            ("--dagger-episodes", "-1"),
            ("--ex-datasets", "-1"),
            ("--ex-fit-steps", "0"),
            ("--ex-error-datasets", "-2"),
        ]
    ),
]


def _small(out: Path, *extra: str) -> list[str]:
    """A run of a few seconds: no exercises, small episode counts."""
    return [
        "frozenlake",
        "--out",
        str(out),
        "--no-progress",
        "--no-exercises",
        "--eval-episodes",
        "50",
        "--sweep-sizes",
        "1,3",
        "--sweep-datasets",
        "2",
        "--sweep-eval-episodes",
        "20",
        "--chain-samples",
        "200",
        "--dagger-rounds",
        "2",
        "--irl-steps",
        "5",
        "--irl-sizes",
        "1",
        "--irl-datasets",
        "2",
        *extra,
    ]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _leftovers(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.*"))


def _staging(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.imitrl-tmp-*"))


def _figures_staged(out: Path) -> bool:
    """Whether a run's staging folder holds a figure. (Not ``any(p.glob(...) for p in
    ...)``: a generator is true even when empty, so the test once killed runs whose lock
    file was made and whose staging folder was not yet, about 2 in 100 under load.)"""
    return any(next(p.glob("*.png"), None) is not None for p in _staging(out))


def _refused(capsys, argv: list[str], expected: str) -> None:
    """``argv`` exits 2 with one line on stderr holding ``expected``, and no traceback."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("imitrl frozenlake: ") and err.count("\n") == 1, err
    assert expected in err and "Traceback" not in err


@pytest.fixture(scope="module")
def previous(tmp_path_factory) -> Path:
    """The output of one finished small run (copied by the tests that need a previous run)."""
    out = tmp_path_factory.mktemp("previous") / "out"
    assert main(_small(out)) == 0
    return out


@pytest.mark.parametrize(
    "flags, expected", BAD_FLAGS, ids=lambda x: " ".join(x) if isinstance(x, list) else ""
)
def test_bad_flag_refused_before_any_work(tmp_path, capsys, flags, expected):
    _refused(capsys, ["frozenlake", "--out", str(tmp_path / "out"), *flags], expected)
    assert list(tmp_path.iterdir()) == []  # neither --out nor a staging folder beside it


def test_bad_out_refused_and_left_alone(tmp_path, capsys, monkeypatch):
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine too")
    (tmp_path / "link").symlink_to(user)
    cases = [
        (a_file, "is a file, not a folder"),
        (a_file / "sub" / "out", f"is under {a_file}, a file"),
        (user, "holds files the study did not write (notes.txt)"),
        (tmp_path / "link", "is a symbolic link"),
        (Path("."), "is the working directory or holds it"),
    ]
    if Path("/proc/self").is_dir():
        cases.append((Path("/proc/study"), "cannot create the output folder beside it"))
    before = {p: _files(p) if p.is_dir() else p.read_bytes() for p in (user, a_file)}
    monkeypatch.chdir(tmp_path)
    for out, expected in cases:
        _refused(capsys, ["frozenlake", "--out", str(out)], expected)
    assert {p: _files(p) if p.is_dir() else p.read_bytes() for p in (user, a_file)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "link", "user"]


_HOSTILE_OUT = r"""
import contextlib, io, json, resource, sys, warnings
sys.path.insert(0, sys.argv[1])
warnings.simplefilter("ignore")
from imitrl.cli import main
import imitrl.experiments.frozenlake.study  # the command's imports, mapped before the limit
with open("/proc/self/status") as f:
    held = next(int(line.split()[1]) << 10 for line in f if line.startswith("VmSize:"))
resource.setrlimit(resource.RLIMIT_AS, (held + (1 << 30),) * 2)  # the imports + 1 GiB
out = {}
for path in sys.argv[2:]:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            out[path] = [main(["frozenlake", "--out", path, "--no-progress"]), err.getvalue()]
    except BaseException as exc:  # MemoryError is what this test exists to catch
        out[path] = [None, f"{type(exc).__name__}: {exc}"]
print(json.dumps(out))
"""


def test_a_fifo_or_a_link_at_results_json_is_refused_at_once(tmp_path):
    """A FIFO at ``--out``'s results.json blocked the run forever, a link to /dev/zero
    read it until memory ran out: neither is a study's output (nor is a file past
    ``outputs.RESULTS_LIMIT``, refused before it is read)."""
    fifo, zero, big = tmp_path / "fifo", tmp_path / "zero", tmp_path / "big"
    for out in (fifo, zero, big):
        out.mkdir()
    os.mkfifo(fifo / "results.json")
    os.symlink("/dev/zero", zero / "results.json")
    with open(big / "results.json", "wb") as f:
        f.truncate((16 << 20) + 1)  # sparse, past outputs.RESULTS_LIMIT
    done = _child.run(
        [sys.executable, "-c", textwrap.dedent(_HOSTILE_OUT), SRC, str(fifo), str(zero), str(big)],
        capture_output=True, text=True, timeout=30,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    for out in (fifo, zero, big):
        refused = f"--out {out} has no results.json of the study: choose another --out"
        assert got[str(out)] == [2, f"imitrl frozenlake: {refused}\n"], (out.name, got)
    assert os.path.islink(zero / "results.json") and (big / "results.json").stat().st_size > 0


def test_a_read_only_folder_under_out_is_one_line_and_exit_1(tmp_path):
    """A read-only file system at ``--out``'s parent is a folder that cannot be written,
    as for every other command: exit 1, one line naming it (was exit 2)."""
    read_only = tmp_path / "read_only"
    read_only.mkdir()
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare(1) to mount a read-only file system")
    inner = (
        f"mount -t tmpfs -o size=64k tmpfs {read_only} && "
        f"mount -o remount,ro {read_only} && "
        f"{sys.executable} -m imitrl frozenlake --out {read_only}/x --no-progress"
    )
    done = subprocess.run(
        [unshare, "-m", "sh", "-c", inner],
        capture_output=True, text=True, timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": SRC},
    )  # fmt: skip
    if done.returncode != 0 and "mount" in done.stderr[-300:] and "imitrl" not in done.stderr:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr[-300:]}")
    assert done.returncode == 1, (done.returncode, done.stderr[-3000:])
    err = done.stderr
    assert err.startswith("imitrl frozenlake: cannot write the study's results to ")
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{read_only} is on a read-only file system" in err, err
    assert list(read_only.iterdir()) == []  # outside the namespace: the folder as it was


def test_unreachable_goal_scores_zero_and_draws_every_figure(tmp_path):
    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs={"desc": UNREACHABLE.split(",")})
    assert not mdp.goal.any()  # the holes are not goals because the G cannot be reached
    out = tmp_path / "out"
    exercises = ["--exercises", "--ex-demo-counts", "1,2", "--ex-datasets", "2"]
    exercises += ["--ex-error-datasets", "2", "--ex-fit-steps", "5", "--max-steps", "20"]
    assert main(_small(out, "--desc", UNREACHABLE, *exercises)) == 0
    r = json.loads((out / "results.json").read_text())
    assert r["expert"]["exact_success"] == 0.0
    assert r["evaluation"]["expert"]["rate"] == r["evaluation"]["clone"]["rate"] == 0.0
    assert all(x["rate"] == 0.0 and x["exact"] == 0.0 for x in r["dagger"]["rounds"])
    assert all(max(r["sweep"][n]["rates"]) == 0.0 for n in ("1", "3"))
    assert np.all(np.array(r["exercises"]["budget"]["dagger"]) == 0.0)
    assert {f"{f}.png" for f in outputs.FIGURES} <= set(os.listdir(out))
    claims = {c["claim"]: c for c in r["prose_checks"]}
    assert claims["expert success rate 0.0%"]["agrees"]  # 0 lies in the Wilson interval at 0/50


def test_figures_at_zero_and_full_success_and_empty_sweeps(tmp_path):
    n = 100
    rates, ci = [0.0, 1.0], [wilson_interval(0, n), wilson_interval(n, n)]
    drawn = [
        figures.plot_dagger([3, 6], rates, ci, rates, 1.0, tmp_path / "dagger.png"),
        figures.plot_sweep([], [], [], 0.0, tmp_path / "sweep.png"),
        figures.plot_chain([], tmp_path / "chain.png"),
        figures.plot_demo_counts([], np.zeros((0, 2)), np.zeros((0, 2)), 0.0, tmp_path / "d.png"),
        figures.plot_occupancy(
            np.array([[b"S", b"G"]]), [np.zeros(2)], [np.zeros(2)], ["x"], tmp_path / "o.png"
        ),
        figures_irl.plot_irl_sweep({}, 0.0, tmp_path / "irl_sweep.png"),
        figures_irl.plot_reward(None, np.zeros(3), np.zeros(3), tmp_path / "r0.png"),
        figures_irl.plot_reward(
            np.array([[b"S", b"G"]]), np.zeros(2), np.zeros(2), tmp_path / "r.png"
        ),
    ]
    assert all(p.stat().st_size > 1000 for p in drawn)


def test_interrupted_run_leaves_previous_results_whole(tmp_path, previous, monkeypatch, capsys):
    out = tmp_path / "out"
    shutil.copytree(previous, out)
    before = _files(out)

    def interrupted(ctx):
        raise KeyboardInterrupt  # Ctrl-C in section 7, after four figures were drawn

    monkeypatch.setattr(study, "dagger_rounds", interrupted)
    capsys.readouterr()
    assert main(_small(out, "--demo-seed", "7")) == 130  # one line, no traceback
    assert capsys.readouterr().err.strip().splitlines()[-1] == "imitrl frozenlake: interrupted"
    assert _files(out) == before and _leftovers(out) == []
    fresh = tmp_path / "fresh"
    assert main(_small(fresh)) == 130
    assert not fresh.exists() and _leftovers(fresh) == []  # no partial --out


def test_sigkill_mid_run_leaves_previous_results_whole(tmp_path, previous, capsys):
    out = tmp_path / "out"
    shutil.copytree(previous, out)
    before = _files(out)
    argv = _small(out, "--dagger-rounds", "1000")  # long enough to be killed mid-run
    proc = _child.Popen([sys.executable, "-m", "imitrl", *argv], stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 240  # generous: a loaded machine is slow to reach a figure
        while not _figures_staged(out):  # a figure drawn: mid-run
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert _files(out) == before
    (killed,) = _staging(out)  # the killed run's staging folder (and its lock file, released)
    with pytest.warns(UserWarning, match=rf"removed {killed.name} \(an unfinished write"):
        assert main(_small(out)) == 0  # the next run removes it, replaces the previous results
    assert _leftovers(out) == [] and _files(out) != before


def test_previous_results_left_aside_by_a_kill_are_put_back(tmp_path, previous):
    """Where the atomic exchange is missing, a kill between the two renames leaves the
    previous results beside --out: the next run puts them back before it starts."""
    out = tmp_path / "out"
    shutil.copytree(previous, tmp_path / ".out.imitrl-old-0000")
    before = _files(tmp_path / ".out.imitrl-old-0000")
    with pytest.warns(UserWarning, match="moved .out.imitrl-old-0000 back to out"):
        with pytest.raises(ValueError, match="the run fails"):
            with outputs.staged(out):  # killed between the two renames: out missing
                assert _files(out) == before
                raise ValueError("the run fails")
    assert _files(out) == before
    assert _leftovers(out) == [] and outputs.is_study_output(out)


def test_a_second_run_of_one_out_is_refused_while_the_first_runs(tmp_path):
    out = tmp_path / "out"
    with outputs.staged(out):  # a run in this process, writing
        second = _child.run(
            [sys.executable, "-m", "imitrl", *_small(out)], capture_output=True, text=True
        )
    assert second.returncode == 2 and "is being written by another process" in second.stderr
    assert _leftovers(out) == []
