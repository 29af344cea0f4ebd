"""The jobs' path fields take a string from Python as the command line's ``Path`` (a
newcomer's review: ``run_bc(BCJob(out="results/x"))`` fitted and evaluated, then failed
on ``str / str`` before writing anything; ``BCJob(dataset="demos")`` on ``.is_dir``)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest

from imitrl.jobs import BCJob, run_bc
from imitrl.jobs.configs import DAggerJob, GAILJob

TINY = dict(env="CartPole-v1", demos=1, num_steps=5, hidden=(8,), eval_episodes=1,
            max_episode_steps=10, progress=False)  # fmt: skip


def test_a_string_out_writes_the_run(tmp_path):
    out = tmp_path / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results = run_bc(BCJob(**TINY, out=str(out)))
    assert json.loads((out / "results.json").read_text())["final_loss"] == results["final_loss"]


@pytest.mark.parametrize("job", [BCJob, DAggerJob, GAILJob])
def test_string_paths_become_paths_and_other_types_are_refused(job):
    config = job(env="CartPole-v1", out="results/x", dataset="demos")
    assert config.out == Path("results/x") and config.dataset == Path("demos")
    with pytest.raises(ValueError, match=r"out must be a path \(str or pathlib\.Path\), got 3"):
        job(env="CartPole-v1", out=3)


def test_steps_0_is_an_untrained_clone_for_bc_and_refused_for_dagger(tmp_path):
    """A hostile review: ``bc --steps 0`` wrote ``"final_loss": NaN``, which strict JSON
    readers refuse; ``dagger --steps 0`` failed after its first round, not naming --steps."""
    from tests._cli import run_main

    out = tmp_path / "bc"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        status, _, err = run_main("bc", "--env", "CartPole-v1", "--demos", "1", "--steps", "0",
                                  "--eval-episodes", "1", "--max-episode-steps", "10",
                                  "--no-progress", "--out", str(out))  # fmt: skip
    assert status == 0, err
    text = (out / "results.json").read_text()
    assert json.loads(text, parse_constant=lambda c: pytest.fail(c))["final_loss"] is None
    status, _, err = run_main("dagger", "--env", "CartPole-v1", "--steps", "0", "--no-progress",
                              "--out", str(tmp_path / "d"))  # fmt: skip
    assert status == 2 and "--steps must be >= 1" in err, err
