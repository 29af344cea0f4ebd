"""imitrl.fs.run_folder's saved work: a fitted learner outlives its evaluation.

``imitrl bc``, ``gail`` and ``airl`` save the checkpoint as soon as the learner is fitted;
an evaluation (or a plot, or anything after the fit) that fails or is interrupted leaves
it in the staging folder, which ``imitrl eval --checkpoint`` reads and which the next run
of the same ``--out`` never discards without ``--overwrite``.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path

import pytest

import imitrl.jobs.bc as bc_job
import imitrl.jobs.gail as gail_job
from imitrl.fs.run_folder import staging_folder
from imitrl.jobs.bc import run_bc
from imitrl.jobs.configs import BCJob
from tests._cli import run_main

TINY = ["--env", "CartPole-v1", "--demos", "1", "--steps", "2", "--batch-size", "8",
        "--hidden", "8", "--eval-episodes", "1", "--max-episode-steps", "10", "--no-progress"]  # fmt: skip


def _failing_evaluation(monkeypatch, module, error: BaseException, after: int = 0) -> list:
    """``module.evaluate_learner`` raising ``error`` from its ``after + 1``-th call on."""
    calls: list = []
    real = module.evaluate_learner

    def evaluate_learner(*args, **kwargs):
        calls.append(1)
        if len(calls) > after:
            raise error
        return real(*args, **kwargs)

    monkeypatch.setattr(module, "evaluate_learner", evaluate_learner)
    return calls


def _weights(folder: Path) -> bytes:
    return (folder / "learner.pt").read_bytes()


def test_a_failed_evaluation_keeps_the_fitted_learner_and_the_next_run_keeps_it_too(
    tmp_path, monkeypatch
):
    out = tmp_path / "run"
    calls = _failing_evaluation(monkeypatch, bc_job, RuntimeError("the simulator crashed"))
    with pytest.raises(RuntimeError, match="the simulator crashed"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run_main("bc", *TINY, "--out", str(out))
    assert calls == [1]
    stage = staging_folder(out)
    assert sorted(p.name for p in stage.iterdir() if p.suffix in {".json", ".pt"}) == [
        "config.json",
        "learner.pt",
    ]  # the checkpoint, without results.json: not a finished run
    assert json.loads((stage / "config.json").read_text())["config"]["num_steps"] == 2
    assert not out.exists()
    monkeypatch.undo()
    saved = _weights(stage)
    # imitrl eval reads the kept learner where it lies
    status, said, err = run_main("eval", "--checkpoint", str(stage), "--eval-episodes", "1",
                                 "--max-episode-steps", "10", "--no-progress")  # fmt: skip
    assert status == 0, err
    assert said.startswith("learner on CartPole-v1: return 10.00"), said  # 10 steps
    # the next run of --out never discards it without --overwrite
    status, _, err = run_main("bc", *TINY, "--out", str(out))
    assert status == 2 and "fitted learner lies in" in err and str(stage) in err, err
    assert _weights(stage) == saved and not out.exists()
    with pytest.warns(UserWarning, match=r"removed an unfinished run's files \(config.json"):
        status, _, err = run_main("bc", *TINY, "--out", str(out), "--overwrite")
    assert status == 0, err
    assert (out / "results.json").is_file() and not stage.exists()


def test_an_interrupted_evaluation_keeps_the_learner_and_says_where(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    _failing_evaluation(monkeypatch, bc_job, KeyboardInterrupt())
    config = BCJob(env="CartPole-v1", demos=1, num_steps=2, batch_size=8, hidden=(8,),
                   eval_episodes=1, max_episode_steps=10, progress=False, out=out)  # fmt: skip
    with pytest.raises(KeyboardInterrupt):
        run_bc(config)
    stage = staging_folder(out)
    assert (stage / "learner.pt").is_file() and not (stage / "results.json").exists()
    err = capsys.readouterr().err
    assert f"the fitted learner is kept in {stage}" in err
    assert f"imitrl eval --checkpoint {stage}" in err


def test_a_run_that_fails_before_its_fit_still_leaves_nothing(tmp_path, monkeypatch):
    out = tmp_path / "run"

    def fit_bc(*args, **kwargs):
        raise RuntimeError("no fit")

    monkeypatch.setattr(bc_job, "fit_bc", fit_bc)
    config = BCJob(env="CartPole-v1", demos=1, num_steps=2, batch_size=8, hidden=(8,),
                   eval_episodes=1, max_episode_steps=10, progress=False, out=out)  # fmt: skip
    with pytest.raises(RuntimeError, match="no fit"):
        run_bc(config)
    assert not staging_folder(out).exists() and not out.exists()
    monkeypatch.undo()
    assert run_bc(replace(config, num_steps=1))["final_loss"] is not None  # no --overwrite needed


def test_gail_keeps_its_trained_learner_when_its_last_evaluation_fails(tmp_path, monkeypatch):
    out = tmp_path / "gail"
    calls = _failing_evaluation(monkeypatch, gail_job, RuntimeError("last"), after=1)
    with pytest.raises(RuntimeError, match="last"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run_main("gail", "--env", "CartPole-v1", "--demos", "1", "--total-steps", "64",
                     "--rollout-steps", "64", "--eval-episodes", "1", "--eval-every", "0",
                     "--max-episode-steps", "10", "--no-progress", "--out", str(out))  # fmt: skip
    assert calls == [1, 1]  # the untrained learner's, then the trained one's
    stage = staging_folder(out)
    assert json.loads((stage / "config.json").read_text())["command"] == "gail"
    assert (stage / "learner.pt").is_file() and not (stage / "results.json").exists()


def test_a_refusal_of_a_finished_out_names_the_learner_kept_beside_it(tmp_path, monkeypatch):
    """A hostile review: with a finished run in --out, the refusal named only that run, and
    the --overwrite it advised discarded the kept learner without a word."""
    out = tmp_path / "run"
    assert run_main("bc", *TINY, "--out", str(out))[0] == 0
    _failing_evaluation(monkeypatch, bc_job, KeyboardInterrupt())
    status, _, err = run_main("bc", *TINY, "--out", str(out), "--overwrite")  # Ctrl-C
    assert status == 130 and "the fitted learner is kept in" in err, (status, err)
    monkeypatch.undo()
    stage = staging_folder(out)
    assert (stage / "learner.pt").is_file() and (out / "results.json").is_file()
    status, _, err = run_main("bc", *TINY, "--out", str(out))
    assert status == 2 and "holds a previous run, finished" in err, err
    assert f"beside it, {stage} holds a fitted learner" in err
    assert "--overwrite discards when the new run starts" in err
