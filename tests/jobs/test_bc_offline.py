"""``imitrl bc --dataset PATH --env none``: a dataset recorded on a robot, with no env to
play or evaluate in, is trained on from the command line (issue 44: ``--env`` had to be
a gymnasium env and evaluation was mandatory). The learner is built for the rows'
observations and the range of their actions; ``imitrl eval --env ENV`` evaluates the
checkpoint later, where there is an env."""

from __future__ import annotations

import contextlib
import io
import json

import pytest
import torch

from imitrl import keys
from imitrl.cli import main
from imitrl.envs import make_env
from imitrl.experts import pendulum_expert
from imitrl.jobs import load_learner, read_checkpoint
from imitrl.runtime import rollout_episodes

pytest.importorskip("pyarrow")


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A LeRobot dataset of Pendulum expert episodes, and its rows: the actions held to
    [-1.8, 1.9] (a robot whose range is not the env's [-2, 2])."""
    from imitrl.datasets import save_lerobot

    env = make_env("Pendulum-v1", seed=3)
    rows = rollout_episodes(env, pendulum_expert(), 4, max_steps=200)
    for key in (keys.EXPERT_ACTION, keys.ACTION):
        rows.set(key, rows.get(key).clamp(-1.8, 1.9))
    return save_lerobot(rows, tmp_path_factory.mktemp("robot") / "demos", fps=20), rows


def test_a_dataset_alone_trains_a_checkpoint_that_eval_plays_in_an_env(recorded, tmp_path):
    root, rows = recorded
    out = tmp_path / "run"
    status, stdout, stderr = run(["bc", "--env", "none", "--dataset", str(root), "--steps",
                                  "400", "--out", str(out), "--no-progress"])  # fmt: skip
    assert status == 0, stderr
    results = json.loads((out / "results.json").read_text())
    assert results["env"] is None and results["learner"] is None and results["expert"] is None
    assert results["demonstrations"]["rows"] == 800 and results["learner_loss"] == "mse"
    assert "not evaluated (--env none)" in stdout and f"--checkpoint {out} --env ENV" in stdout

    # the action bounds are the recorded actions' range, kept in the weights
    env = make_env("Pendulum-v1", seed=0)
    learner = load_learner(out, env)  # imitrl.jobs' own name for it, as the tutorial says
    assert read_checkpoint(out).config["env"] is None
    from imitrl.policies.heads import Squash

    (squash,) = [m for m in learner.policy.modules() if isinstance(m, Squash)]
    labels = rows.get(keys.EXPERT_ACTION)
    assert torch.equal(squash.low, labels.amin(0)) and torch.equal(squash.high, labels.amax(0))
    assert squash.low.tolist() == [-1.7999999523162842] and squash.high.tolist() == [
        1.899999976158142
    ]

    # eval needs the env named, and then plays the learner there: far above random
    status, _, stderr = run(["eval", "--checkpoint", str(out), "--no-progress"])
    assert status == 2 and "trained on a dataset alone" in stderr and "--env ENV" in stderr
    status, stdout, stderr = run(["eval", "--checkpoint", str(out), "--env", "Pendulum-v1",
                                  "--eval-episodes", "5", "--no-progress"])  # fmt: skip
    assert status == 0, stderr
    assert float(stdout.split(" return ")[1].split()[0]) > -400.0, stdout


@pytest.mark.parametrize(
    "argv, said",
    [
        (["bc", "--env", "none"], "--env none trains on --dataset alone: give --dataset"),
        (["bc", "--env", "none", "--dataset", "d", "--expert", "pendulum"],
         "--expert pendulum needs an env to act in"),
        (["dagger", "--env", "none", "--dataset", "d"], "dagger plays the learner in an env"),
        (["gail", "--env", "none", "--dataset", "d"], "gail and airl play the learner in an env"),
    ],
)  # fmt: skip
def test_what_needs_an_env_refuses_env_none_in_one_line(argv, said):
    status, _, stderr = run(argv)
    assert status == 2 and said in stderr and "Traceback" not in stderr
