"""``--nproc N``: ``imitrl bc`` and ``imitrl dagger`` in N data-parallel ranks from the
command line, launched as torchrun launches them (issue 45): the same numbers as one
process at N times the batch, from expert demonstrations and from a LeRobot dataset; a
rank killed mid-fit ends the run at once with one line naming it; bad rank counts are
one line each."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests import _child

TINY = ["--env", "Pendulum-v1", "--demos", "1", "--steps", "40", "--eval-episodes", "2",
        "--max-episode-steps", "40", "--no-progress"]  # fmt: skip


def imitrl(*argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "imitrl", *argv]
    return _child.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)


def _results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


@pytest.mark.parametrize(
    "command",
    ["bc", pytest.param("dagger", marks=pytest.mark.slow)],  # dagger: -m slow
)
def test_two_ranks_give_one_process_at_twice_the_batch(command, tmp_path):
    extra = ["--rounds", "2", "--episodes-per-round", "1"] if command == "dagger" else []
    two = imitrl(command, *TINY, *extra, "--nproc", "2", "--batch-size", "8",
                 "--out", str(tmp_path / "two"))  # fmt: skip
    assert two.returncode == 0, two.stderr
    assert two.stdout.count("wrote ") == 1  # rank 0 alone reports
    one = imitrl(command, *TINY, *extra, "--batch-size", "16", "--out", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr
    a, b = _results(tmp_path / "two"), _results(tmp_path / "one")
    assert a["final_loss"] == pytest.approx(b["final_loss"], rel=1e-5)
    assert a["learner"]["mean_return"] == pytest.approx(b["learner"]["mean_return"], rel=1e-4)
    assert json.loads((tmp_path / "two" / "config.json").read_text())["config"]["nproc"] == 2


@pytest.mark.slow  # a launch of 3 processes on 2 cores: run with -m slow
@pytest.mark.parametrize("command", ["gail", "airl"])
def test_adversarial_imitation_on_two_ranks_counts_both_ranks_steps(command, tmp_path):
    done = imitrl(command, "--env", "CartPole-v1", "--total-steps", "1024", "--rollout-steps",
                  "256", "--num-envs", "2", "--eval-episodes", "2", "--eval-every", "2",
                  "--nproc", "2", "--out", str(tmp_path / "run"), "--no-progress")  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("wrote ") == 1  # rank 0 alone reports
    results = _results(tmp_path / "run")
    assert results["env_steps"] == 1024  # 2 rounds of 2 ranks x 256 steps
    assert [r["env_steps"] for r in results["rounds"]] == [512, 1024]
    assert results["rounds"][1]["info"]["evaluation"] == results["learner"]


@pytest.mark.slow  # Ray workers beside 3 processes on 2 cores: run with -m slow
def test_dagger_rounds_on_ray_workers_feed_two_ranks(tmp_path):
    """Rank 0's Ray workers play the rounds, every rank fits on their rows: one process
    with the same workers at twice the batch, round for round."""
    pytest.importorskip("ray")
    argv = [*TINY, "--rounds", "2", "--episodes-per-round", "2", "--workers", "2"]
    two = imitrl("dagger", *argv, "--nproc", "2", "--batch-size", "8",
                 "--out", str(tmp_path / "two"), timeout=600)  # fmt: skip
    assert two.returncode == 0, two.stderr
    one = imitrl("dagger", *argv, "--batch-size", "16", "--out", str(tmp_path / "one"),
                 timeout=600)  # fmt: skip
    assert one.returncode == 0, one.stderr
    a, b = _results(tmp_path / "two"), _results(tmp_path / "one")
    assert [r["rows_trained"] for r in a["rounds"]] == [r["rows_trained"] for r in b["rounds"]]
    for ra, rb in zip(a["rounds"], b["rounds"]):
        assert ra["final_loss"] == pytest.approx(rb["final_loss"], rel=1e-5)


@pytest.mark.slow  # several launches of 3 processes on 2 cores: run with -m slow (they starve the default run's race tests)
def test_two_ranks_train_on_a_lerobot_dataset(tmp_path):
    pytest.importorskip("pyarrow")
    from imitrl.datasets import save_lerobot
    from imitrl.envs import make_env
    from imitrl.experts import pendulum_expert
    from imitrl.runtime import rollout_episodes

    env = make_env("Pendulum-v1", seed=3, max_episode_steps=40)
    root = save_lerobot(rollout_episodes(env, pendulum_expert(), 2), tmp_path / "d", fps=20)
    done = imitrl("bc", "--env", "none", "--dataset", str(root), "--nproc", "2", "--steps",
                  "30", "--batch-size", "8", "--out", str(tmp_path / "run"), "--no-progress")  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert _results(tmp_path / "run")["demonstrations"]["rows"] == 80


def test_a_rank_killed_mid_fit_ends_the_run_naming_it(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-m", "imitrl", "bc", *TINY[:-1], "--steps", "10000000",
            "--nproc", "2", "--out", str(tmp_path / "run"), "--no-progress"]  # fmt: skip
    proc = _child.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)  # fmt: skip
    try:
        rank = _wait_for_rank(proc.pid, 1, deadline=300)
        os.kill(rank, signal.SIGKILL)
        start = time.monotonic()
        _, stderr = proc.communicate(timeout=60)  # the others stop within a minute
    finally:
        if proc.poll() is None:
            proc.kill()  # the ranks end with their launcher (they watch it)
    assert proc.returncode == 1 and time.monotonic() - start < 60
    assert "rank 1 (killed by SIGKILL) ended the run" in stderr, stderr
    assert not (tmp_path / "run").exists()  # nothing half-written in --out


def _wait_for_rank(parent: int, local_rank: int, deadline: float, settle: float = 6) -> int:
    """The pid of rank ``local_rank`` (the launcher's child with that ``LOCAL_RANK``)."""
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        ranks = []
        for pid in os.listdir("/proc"):
            if pid.isdigit():
                try:
                    stat = Path(f"/proc/{pid}/stat").read_text().split()
                    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
                except OSError:
                    continue
                if int(stat[3]) == parent and f"LOCAL_RANK={local_rank}".encode() in environ:
                    ranks.append(int(pid))
        if ranks:
            time.sleep(settle)  # into the fit: past imports, the demonstrations, first steps
            return ranks[0]
        time.sleep(0.5)
    raise AssertionError("the ranks did not start")


@pytest.mark.parametrize(
    "argv, said",
    [
        (["bc", "--nproc", "0"], "--nproc must be an integer >= 1, got 0"),
        (["bc", "--nproc", "4096"], "--nproc must be an integer"),
        (["bc", "--nproc", str(len(os.sched_getaffinity(0)) + 1)], "more CPU ranks than the"),
    ],
)
def test_bad_rank_counts_are_one_line(argv, said):
    import contextlib
    import io

    from imitrl.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main(argv)
    assert status == 2 and said in err.getvalue() and "Traceback" not in err.getvalue()


DAGGER = [*TINY, "--rounds", "1", "--episodes-per-round", "1"]


@pytest.mark.slow  # several launches of 3 processes on 2 cores: run with -m slow (they starve the default run's race tests)
def test_a_dagger_run_resumes_at_another_world_size(tmp_path):
    """Saved at 2 ranks (batch 8 each), resumed at 1 (batch 16), and the reverse: both
    equal the run never interrupted, at 16 in one process."""
    whole = imitrl("dagger", *DAGGER[:-3], "2", "--episodes-per-round", "1", "--batch-size",
                   "16", "--out", str(tmp_path / "whole"))  # fmt: skip
    assert whole.returncode == 0, whole.stderr
    want = _results(tmp_path / "whole")
    for first, then in ((["--nproc", "2", "--batch-size", "8"], ["--batch-size", "16"]),
                        (["--batch-size", "16"], ["--nproc", "2", "--batch-size", "8"])):  # fmt: skip
        out = tmp_path / f"run{len(first)}"
        done = imitrl("dagger", *DAGGER, *first, "--out", str(out))  # round 0 and its episodes
        assert done.returncode == 0, done.stderr
        more = imitrl("dagger", *DAGGER[:-3], "2", "--episodes-per-round", "1", *then,
                      "--resume", "--out", str(out))  # fmt: skip
        assert more.returncode == 0, more.stderr
        got = _results(out)
        assert got["final_loss"] == pytest.approx(want["final_loss"], rel=1e-5)
        assert [r["rows_trained"] for r in got["rounds"]] == [
            r["rows_trained"] for r in want["rounds"]
        ]
    # a world size that asks for another global batch: one line saying what to give
    wrong = imitrl("dagger", *DAGGER[:-3], "2", "--episodes-per-round", "1", "--nproc", "2",
                   "--batch-size", "16", "--resume", "--out", str(tmp_path / "run4"))  # fmt: skip
    assert wrong.returncode == 2, wrong.stderr
    assert "global batch of 16 rows" in wrong.stderr and "give --batch-size 8" in wrong.stderr


@pytest.mark.slow  # 11 s of three processes; run it with -m slow (the watch is in every rank)
def test_ranks_end_with_a_launcher_killed_outright(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-m", "imitrl", "bc", *TINY[:-1], "--steps", "10000000",
            "--nproc", "2", "--out", str(tmp_path / "run"), "--no-progress"]  # fmt: skip
    proc = _child.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    ranks = [_wait_for_rank(proc.pid, k, deadline=300, settle=s) for k, s in ((0, 0), (1, 4))]
    proc.kill()
    proc.wait()
    end = time.monotonic() + 60
    while time.monotonic() < end and any(map(_running, ranks)):
        time.sleep(0.5)
    alive = [r for r in ranks if _running(r)]
    for r in alive:
        os.kill(r, signal.SIGKILL)
    assert not alive, f"ranks outlived their launcher: {alive} of {ranks}"


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie, ended but not yet reaped, is not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def test_a_rank_other_than_0_names_what_it_refused(monkeypatch):
    """A hostile review: a rank of another machine that refused its input said nothing."""
    import contextlib
    import io

    from imitrl.cli import main

    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main(["bc", "--steps", "-1"])
    assert status == 2 and err.getvalue().startswith("imitrl bc: rank 1: --steps must be")


def test_only_a_collectives_failure_is_called_a_lost_peer():
    import torch.distributed as dist

    from imitrl.cli.launch import peer_lost

    assert peer_lost(dist.DistError("anything"))
    assert peer_lost(RuntimeError("[gloo] Connection closed by peer [127.0.0.1]:29500"))
    assert not peer_lost(RuntimeError("The expanded size of the tensor (59) must match"))


@pytest.mark.slow  # three launches of 3 processes on 2 cores: run with -m slow
def test_a_killed_two_rank_dagger_run_resumes_as_if_never_stopped(tmp_path):
    """A hostile review: the resumed rank 1 started afresh while rank 0 continued its
    checkpoint, and a wrong learner was published before the run failed."""
    flags = ["dagger", "--env", "CartPole-v1", "--demos", "1", "--rounds", "3",
             "--episodes-per-round", "1", "--steps", "2000", "--max-episode-steps", "20",
             "--eval-episodes", "1", "--no-progress", "--batch-size", "16", "--nproc", "2"]  # fmt: skip
    whole = imitrl(*flags, "--out", str(tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    out = tmp_path / "killed"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = _child.Popen([sys.executable, "-m", "imitrl", *flags, "--out", str(out)],
                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)  # fmt: skip
    state = out.parent / f".{out.name}.imitrl-run" / "run" / "state.json"
    try:
        rank = _wait_for_rank(proc.pid, 1, deadline=300, settle=0)
        end = time.monotonic() + 300
        while time.monotonic() < end:
            try:
                if json.loads(state.read_text())["next_round"] >= 1:
                    break
            except (OSError, ValueError, KeyError):
                pass
            time.sleep(0.05)
        os.kill(rank, signal.SIGKILL)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not out.exists() and state.exists()
    more = imitrl(*flags, "--out", str(out), "--resume")
    assert more.returncode == 0, more.stderr
    got, want = _results(out), _results(tmp_path / "whole")
    assert [r["final_loss"] for r in got["rounds"]] == pytest.approx(
        [r["final_loss"] for r in want["rounds"]], rel=1e-5
    )
