"""Runs saved by imitrl at d6e5639 load and resume (issue 43): their learners carried a
value head and its optimizer, which a learner built today has only when a job needs one
(``tests/fixtures/d6e5639/README.md`` says how the runs were made)."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from imitrl.cli import main
from imitrl.envs import make_env
from imitrl.jobs.checkpoint import load_learner

OLD = Path(__file__).resolve().parents[1] / "fixtures" / "d6e5639"
E0CEEBC = OLD.parent / "e0ceebc"
"""runs saved before a loss's generator was (``tests/fixtures/e0ceebc/README.md``)"""
COMMON = ["--demos", "1", "--max-episode-steps", "50", "--eval-episodes", "2", "--no-progress"]


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


@pytest.mark.parametrize(
    "name, env_id",
    [("cart_bc", "CartPole-v1"), ("pend_bc", "Pendulum-v1"), ("cart_gail", "CartPole-v1")],
)
def test_an_old_run_loads_with_its_weights_and_reproduces_its_evaluation(tmp_path, name, env_id):
    saved = torch.load(OLD / name / "learner.pt", weights_only=True)
    assert any(k.startswith("value.") for k in saved)  # what d6e5639 saved
    learner = load_learner(OLD / name, make_env(env_id, seed=0))
    assert learner.value is None
    for key, tensor in learner.state_dict().items():
        assert torch.equal(tensor, saved[key]), key  # every weight it has, as saved
    status, _, err = run(["eval", "--checkpoint", str(OLD / name), "--eval-episodes", "2",
                            "--max-episode-steps", "50", "--no-progress",
                            "--out", str(tmp_path / "ev")])  # fmt: skip
    assert status == 0, err
    evaluated = json.loads((tmp_path / "ev" / "eval.json").read_text())["evaluation"]
    recorded = json.loads((OLD / name / "results.json").read_text())["learner"]
    if env_id == "Pendulum-v1":
        # Pendulum's returns sum 50 float64 dynamics steps driven by float32 actions, whose
        # last bits depend on the CPU's matmul kernels (AVX2 vs AVX-512): seen to differ in
        # the 10th digit between the machine that saved the run and another. CartPole's
        # integer returns are equal exactly.
        assert evaluated["mean_return"] == pytest.approx(recorded["mean_return"], rel=1e-7)
    else:
        assert evaluated["mean_return"] == recorded["mean_return"]


def test_an_old_dagger_run_resumes_and_equals_the_longer_run(tmp_path):
    """d6e5639's 2-round run (its ``run/`` checkpoint holds the value head's weights and
    ``opt_v``), resumed to 3 rounds today, gives today's uninterrupted 3-round run."""
    out = tmp_path / "old"
    shutil.copytree(OLD / "cart_dagger", out)
    flags = ["dagger", "--env", "CartPole-v1", *COMMON, "--episodes-per-round", "1",
             "--steps", "20", "--rounds", "3"]  # fmt: skip
    status, _, err = run([*flags, "--out", str(out), "--resume"])
    assert status == 0, err
    status, _, err = run([*flags, "--out", str(tmp_path / "whole")])
    assert status == 0, err
    resumed = json.loads((out / "results.json").read_text())
    whole = json.loads((tmp_path / "whole" / "results.json").read_text())
    # the rounds d6e5639 played keep its evaluations, whose intervals used its Student-t
    # quantile (Simpson's rule: t_0.975,1 = 12.706204736174719, today 12.706204736174698)
    for a, b in zip(resumed["rounds"], whole["rounds"], strict=True):
        ci_a, ci_b = a["evaluation"].pop("return_ci"), b["evaluation"].pop("return_ci")
        assert ci_a == pytest.approx(ci_b, rel=1e-13)
    for key in ("rounds", "learner", "final_loss"):
        assert resumed[key] == whole[key], key


def test_a_run_saved_before_loss_generators_were_loads_and_reproduces_its_evaluation(tmp_path):
    saved = torch.load(E0CEEBC / "pend_flow" / "learner.pt", weights_only=True)
    assert not any(k.endswith("_extra_state") for k in saved)  # what e0ceebc saved
    learner = load_learner(E0CEEBC / "pend_flow", make_env("Pendulum-v1", seed=0))
    for key, tensor in saved.items():
        assert torch.equal(learner.state_dict()[key], tensor), key
    status, _, err = run(["eval", "--checkpoint", str(E0CEEBC / "pend_flow"),
                            "--eval-episodes", "2", "--max-episode-steps", "50",
                            "--no-progress", "--out", str(tmp_path / "ev")])  # fmt: skip
    assert status == 0, err
    evaluated = json.loads((tmp_path / "ev" / "eval.json").read_text())["evaluation"]
    recorded = json.loads((E0CEEBC / "pend_flow" / "results.json").read_text())["learner"]
    assert evaluated["mean_return"] == pytest.approx(recorded["mean_return"], rel=1e-7)


def test_a_dagger_run_saved_before_loss_generators_were_resumes_and_saves_them(tmp_path):
    out = tmp_path / "old"
    shutil.copytree(E0CEEBC / "pend_flow_dagger", out)
    status, _, err = run(["dagger", "--env", "Pendulum-v1", "--loss", "flow", "--hidden",
                            "16,16", *COMMON, "--episodes-per-round", "1", "--steps", "20",
                            "--rounds", "3", "--out", str(out), "--resume"])  # fmt: skip
    assert status == 0, err
    rounds = json.loads((out / "results.json").read_text())["rounds"]
    old = json.loads((E0CEEBC / "pend_flow_dagger" / "results.json").read_text())["rounds"]
    assert len(rounds) == 3 and rounds[0] == old[0]  # the rounds it played are kept
    for key in ("evaluation", "final_loss", "rows_trained"):  # (the last one now has a next)
        assert rounds[1][key] == old[1][key], key
    saved = torch.load(out / "learner.pt", weights_only=True)
    assert saved["loss._extra_state"].dtype == torch.uint8  # saved from now on
