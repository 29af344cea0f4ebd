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
