"""Resumable DAgger: a run SIGKILLed after any round and resumed gives the uninterrupted
run's buffer, learner weights and evaluation, identical to the bit."""

from __future__ import annotations

import functools
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from imitrl.algorithms import dagger
from imitrl.envs import make_env
from imitrl.evaluation import evaluate
from imitrl.tabular import TabularMDP, success_probability
from tests import _child, _resume_run

ROOT = Path(__file__).resolve().parents[2]


def _fingerprint(kind: str, result) -> dict:
    """Everything compared: rows, weights (and optimizer moments) and an evaluation."""
    learner = result.learner
    out = {
        "rows": result.buffer.data.clone(),
        "weights": {k: v.clone() for k, v in learner.state_dict().items()},
        "records": [
            (r.rows_trained, r.rows_collected, r.bc.losses.tolist()) for r in result.rounds
        ],
    }
    if kind == "cartpole":
        env = make_env("CartPole-v1", seed=0, num_envs=4, max_episode_steps=40)
        out["eval"] = evaluate(env, learner, 8, seed=11).mean_return
    else:
        mdp = TabularMDP.from_gym("FrozenLake-v1", gamma=0.95)
        out["eval"] = success_probability(mdp, learner.greedy_table())
    return out


def _assert_identical(a: dict, b: dict) -> None:
    assert a["rows"].shape == b["rows"].shape and bool((a["rows"] == b["rows"]).all())
    assert a["weights"].keys() == b["weights"].keys()
    for key in a["weights"]:
        assert torch.equal(a["weights"][key], b["weights"][key]), key
    assert a["records"] == b["records"] and a["eval"] == b["eval"]


@functools.cache
def _reference(kind: str) -> dict:
    return _fingerprint(kind, _resume_run.run(kind))


# killed after the first round (CartPole) and after the last-but-one (the lake): the first
# and the last resume of a run, on both kinds of env (the rounds between take the same
# path; each kill is a subprocess of ~15 s, so not every pair is run)
@pytest.mark.parametrize("kind, kill_at", [("cartpole", 1), ("lake", _resume_run.ROUNDS - 1)])
def test_killed_after_any_round_and_resumed_is_identical_to_the_bit(kind, kill_at, tmp_path):
    expected = _reference(kind)
    ckpt = tmp_path / "run"
    proc = _child.run(
        [sys.executable, "-m", "tests._resume_run", kind, str(ckpt), str(kill_at)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    resumed = _resume_run.run(kind, ckpt, resume=True)
    assert [r.round for r in resumed.rounds] == list(range(_resume_run.ROUNDS))
    _assert_identical(_fingerprint(kind, resumed), expected)


def test_a_finished_run_resumes_to_its_result_and_refuses_to_be_overwritten(tmp_path):
    ckpt = tmp_path / "run"
    done = _resume_run.run("lake", ckpt)
    again = _resume_run.run("lake", ckpt, resume=True)  # nothing left to run
    _assert_identical(_fingerprint("lake", again), _fingerprint("lake", done))
    with pytest.raises(ValueError, match="pass resume=True"):
        _resume_run.run("lake", ckpt)
    with pytest.raises(ValueError, match="needs the checkpoint_dir"):
        _resume_run.run("lake", None, resume=True)


def test_resuming_with_another_config_or_other_demonstrations_is_refused(tmp_path):
    ckpt = tmp_path / "run"
    _resume_run.run("lake", ckpt)
    source, expert, make_learner, buffer, config = _resume_run.build("lake")
    other = type(config)(rounds=config.rounds, episodes_per_round=2, bc=config.bc)
    with pytest.raises(ValueError, match=r"another config \(differs in \['episodes_per_round'\]\)"):
        dagger(source, expert, make_learner, buffer, other, checkpoint_dir=ckpt, resume=True)
    source, expert, make_learner, _, config = _resume_run.build("lake")
    wrong = _resume_run.build("lake")[3]
    wrong.extend(source.collect(expert.as_actor(), 1, round_index=0, first_episode=3))
    with pytest.raises(ValueError, match="does not hold the demonstrations"):
        dagger(source, expert, make_learner, wrong, config, checkpoint_dir=ckpt, resume=True)


def test_imitrl_dagger_resume_after_a_kill_gives_the_uninterrupted_results(tmp_path):
    """The CLI: kill `imitrl dagger` once its first round is checkpointed, then --resume."""
    import json
    import time

    from imitrl.cli import main
    from imitrl.fs.run_folder import staging_folder

    flags = [
        "dagger", "--env", "CartPole-v1", "--expert", "cartpole", "--demos", "1",
        "--rounds", "4", "--episodes-per-round", "2", "--steps", "40", "--batch-size", "32",
        "--hidden", "16,16", "--eval-episodes", "4", "--max-episode-steps", "60", "--no-progress",
    ]  # fmt: skip
    assert main([*flags, "--out", str(tmp_path / "whole")]) == 0
    killed = tmp_path / "killed"
    proc = _child.Popen(
        [sys.executable, "-m", "imitrl", *flags, "--out", str(killed)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    manifest = staging_folder(killed) / "run" / "manifest.json"  # the run in progress
    deadline = time.monotonic() + 240
    while not manifest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert manifest.exists(), "the run ended before its first checkpoint"
    assert not killed.exists(), "the run finished before the kill"  # --out: finished runs only
    assert main([*flags, "--out", str(killed)]) == 2  # a saved run is not overwritten
    assert main([*flags, "--out", str(killed), "--resume"]) == 0
    whole = json.loads((tmp_path / "whole" / "results.json").read_text())
    resumed = json.loads((killed / "results.json").read_text())
    for key in ("rounds", "learner", "expert", "final_loss"):
        assert resumed[key] == whole[key], key


@pytest.mark.parametrize("kind", ["cartpole", "lake"])
def test_a_finished_run_resumed_with_more_rounds_equals_the_longer_run(tmp_path, kind):
    """A run saved at its last round (which collects nothing), resumed with more rounds:
    the missing relabel episodes are played first, so the result is the longer run's,
    to the bit (was: the grown rounds refitted the same rows)."""
    import dataclasses

    from imitrl.algorithms import dagger

    ckpt = tmp_path / "run"
    source, expert, make_learner, buffer, config = _resume_run.build(kind)
    short = dataclasses.replace(config, rounds=2)
    dagger(source, expert, make_learner, buffer, short, checkpoint_dir=ckpt)
    source, expert, make_learner, buffer, config = _resume_run.build(kind)
    grown = dagger(source, expert, make_learner, buffer, config, checkpoint_dir=ckpt, resume=True)
    _assert_identical(_fingerprint(kind, grown), _reference(kind))


def test_a_resume_with_other_shared_settings_names_them(tmp_path):
    """``DAggerConfig.shared``: the caller's settings (``imitrl dagger``'s env and
    evaluation protocol) are held like the algorithm's; the message names each one."""
    import dataclasses

    ckpt = tmp_path / "run"
    source, expert, make_learner, buffer, config = _resume_run.build("lake")
    shared = {"env": "FrozenLake-v1", "eval_seed": 1}
    dagger(source, expert, make_learner, buffer, dataclasses.replace(config, shared=shared),
           checkpoint_dir=ckpt)  # fmt: skip
    for other, differs in (({**shared, "eval_seed": 2}, "['eval_seed']"),
                           ({}, "['env', 'eval_seed']")):  # fmt: skip
        source, expert, make_learner, buffer, config = _resume_run.build("lake")
        with pytest.raises(
            ValueError, match=rf"another config \(differs in {re.escape(differs)}\)"
        ):
            dagger(source, expert, make_learner, buffer,
                   dataclasses.replace(config, shared=other), checkpoint_dir=ckpt,
                   resume=True)  # fmt: skip


def test_a_learner_for_make_learner_and_a_buffer_holding_its_rounds_are_named(tmp_path):
    """A hostile review: a Learner given for make_learner failed inside torch (a module is
    callable); resuming with the buffer the run had extended said "round record 0 trained
    on 60 rows; its rounds make 300"."""
    ckpt = tmp_path / "run"
    result = _resume_run.run("lake", ckpt)
    source, expert, make_learner, buffer, config = _resume_run.build("lake")
    with pytest.raises(ValueError, match="make_learner must be a function of no arguments"):
        dagger(source, expert, make_learner(), buffer, config)
    demos = len(buffer)
    with pytest.raises(
        ValueError, match=f"the buffer holds {len(result.buffer)} rows; the run"
    ) as err:
        dagger(source, expert, make_learner, result.buffer, config, checkpoint_dir=ckpt,
               resume=True)  # fmt: skip
    assert f"started from {demos} rows of demonstrations" in str(err.value)
