"""A newcomer's first hour (issue 27, items 8-10, 12-14, 16): every mistake a new user
makes at the command line or the API gets one clear line naming what to do instead.
"""

from __future__ import annotations

import contextlib
import io
import logging
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger
from imitrl.cli import main
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.evaluation import evaluate
from imitrl.experts import cartpole_expert
from imitrl.learners import build
from imitrl.policies import Expert
from imitrl.runtime import rollout_episodes
from tests.data.test_checkpoint import demo_rows

TINY = ["--demos", "1", "--steps", "2", "--batch-size", "8", "--hidden", "8",
        "--eval-episodes", "1", "--max-episode-steps", "10", "--no-progress"]  # fmt: skip


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


def refused(argv: list[str], *expected: str) -> str:
    status, _, err = run(argv)
    assert status == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for text in expected:
        assert text in err, err
    return err


# --------------------------------------------------- item 8: the expert for the env
def test_the_default_expert_is_the_envs_own(tmp_path):
    status, out, err = run(["bc", "--env", "Acrobot-v1", *TINY, "--out", str(tmp_path / "a")])
    assert status == 0, err
    assert "expert: return" in out


def test_an_expert_for_another_env_is_named_with_the_right_one(tmp_path):
    refused(
        ["bc", "--env", "Acrobot-v1", "--expert", "cartpole", *TINY, "--out", str(tmp_path)],
        "--expert cartpole cannot label Acrobot-v1's observations",
        "use --expert acrobot",
    )


def test_an_env_without_a_built_in_expert_says_what_to_pass(tmp_path):
    refused(
        ["bc", "--env", "MountainCarContinuous-v0", *TINY, "--out", str(tmp_path)],
        "--env MountainCarContinuous-v0 has no built-in expert",
        "--expert module:function",
    )


# ----------------------------------- item 9: a plain function given as a builder
def test_a_plain_function_without_expert_kind_callable_is_named(tmp_path, monkeypatch):
    (tmp_path / "myexperts.py").write_text(
        textwrap.dedent(
            """
            import torch

            def push(obs):
                return (obs[..., 2] > 0).long()
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    base = ["bc", "--expert", "myexperts:push", *TINY, "--out", str(tmp_path / "o")]
    refused(base, "--expert myexperts:push takes argument(s) ['obs']", "--expert-kind callable")
    status, _, err = run([*base, "--expert-kind", "callable"])
    assert status == 0, err


# ------------------------------------------------- item 10: one rule for --out
def test_every_command_refuses_a_previous_run_in_out_unless_overwrite(tmp_path):
    out = str(tmp_path / "run")
    assert run(["bc", *TINY, "--out", out])[0] == 0
    for command in (["bc"], ["dagger", "--rounds", "2", "--episodes-per-round", "1"]):
        refused([*command, *TINY, "--out", out], "holds a previous run", "--overwrite")
    status, _, err = run(["dagger", "--rounds", "2", "--episodes-per-round", "1", *TINY,
                          "--out", out, "--overwrite"])  # fmt: skip
    assert status == 0, err
    assert (tmp_path / "run" / "run" / "manifest.json").exists()  # the new run's checkpoint
    refused(["bc", *TINY, "--out", out], "--resume to continue it")


def test_overwrite_never_deletes_files_a_run_did_not_write(tmp_path):
    (tmp_path / "thesis.tex").write_text("years of work")
    refused(["bc", *TINY, "--out", str(tmp_path), "--overwrite"], "thesis.tex", "never deletes")
    assert (tmp_path / "thesis.tex").read_text() == "years of work"


def test_eval_refuses_an_eval_json_in_out_unless_overwrite(tmp_path):
    argv = ["eval", "--expert", "cartpole", "--env", "CartPole-v1", "--eval-episodes", "1",
            "--max-episode-steps", "5", "--no-progress", "--out", str(tmp_path)]  # fmt: skip
    assert run(argv)[0] == 0
    refused(argv, "holds an eval.json", "--overwrite")
    assert run([*argv, "--overwrite"])[0] == 0


# ------------------------------------------ item 12: scores that cannot be normalised
def test_bc_vs_dagger_says_why_a_score_is_nan(capsys):
    benchmarks = Path(__file__).resolve().parents[2] / "benchmarks"
    sys.path.insert(0, str(benchmarks))
    try:
        import bc_vs_dagger as bench
    finally:
        sys.path.remove(str(benchmarks))
    import dataclasses

    (task,), _ = bench.tasks_from(["Acrobot-v1"], None, {"episodes_per_round": 1, "fit_steps": 2})
    cfg = dataclasses.replace(bench.QUICK, max_episode_steps=5, relabel_rounds=1, seeds=1)
    record = bench.run_seed(task, 0, cfg)
    assert record["expert_return"] == record["random_return"]  # -5 both: no swing-up in 5 steps
    err = capsys.readouterr().err
    assert "normalised scores are undefined (nan)" in err and "--max-episode-steps" in err


# -------------------------------------------------- item 13: help and progress
def test_help_shows_defaults_as_they_are_typed(capsys):
    with pytest.raises(SystemExit):
        main(["frozenlake", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 10,100,1000)" in text and "(10, 100, 1000)" not in text
    with pytest.raises(SystemExit):
        main(["bc", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "which has none (default: none)" in text  # --hidden: the network's own


def test_frozenlake_takes_max_episode_steps_like_every_command(tmp_path):
    from imitrl.cli import build_parser

    parser = build_parser(["frozenlake"])
    a = parser.parse_args(["frozenlake", "--max-episode-steps", "50"])
    b = parser.parse_args(["frozenlake", "--max-steps", "50"])
    assert a.max_steps == b.max_steps == 50


def test_eval_shows_progress_on_stderr(tmp_path):
    status, out, err = run(["eval", "--expert", "cartpole", "--env", "CartPole-v1",
                            "--eval-episodes", "3", "--max-episode-steps", "5"])  # fmt: skip
    assert status == 0 and "evaluate" in err and "/3 " in err, err  # a bar over the 3 episodes
    assert "evaluate" not in out


# ---------------------------------------------------- item 14: nothing on stdout
def test_a_buffer_prints_nothing_on_its_first_write(capfd):
    import torchrl  # noqa: F401  (its logger: INFO, unless a CLI test quietened it)

    log = logging.getLogger("torchrl")
    level = log.level
    log.setLevel(logging.INFO)  # as a script that imported imitrl finds it
    try:
        DemonstrationBuffer().extend(demo_rows(5))
        assert capfd.readouterr().out == ""
        assert log.level == logging.INFO  # and the user's level is kept
    finally:
        log.setLevel(level)


# ------------------------------------------------ item 16: unclear crashes
@pytest.mark.parametrize(
    ("make", "message"),
    [
        (
            lambda: BCConfig(batch_size=2.5),
            r"BCConfig.batch_size must be an integer in \[1, 1_048_576\] or none",
        ),
        (
            lambda: BCConfig(num_steps=10.0),
            r"BCConfig.num_steps must be an integer in \[0, 10_000_000\]",
        ),
        (lambda: DAggerConfig(rounds=2.5), r"DAggerConfig.rounds must be an integer >= 1"),
        (lambda: DAggerConfig(beta=0.5), r"DAggerConfig.beta must be a schedule"),
        (lambda: make_env("CartPole-v1", seed=None), r"seed must be an integer"),
    ],
)
def test_a_config_of_the_wrong_type_is_named(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_a_train_callback_returning_none_is_named():
    env = make_env("CartPole-v1", seed=0, max_episode_steps=10)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, cartpole_expert(), 1))
    with pytest.raises(ValueError, match=r"train callback must return the fit's BCResult"):
        dagger(EnvSource(env), cartpole_expert(), lambda: build("for_env", env, hidden=(8,)),
               buffer, DAggerConfig(rounds=1), train=lambda learner, buf: None)  # fmt: skip


def test_evaluate_names_a_policy_module_built_for_another_env():
    env = make_env("CartPole-v1", seed=0)
    policy = TensorDictModule(torch.nn.Linear(6, 2), in_keys=["observation"], out_keys=["action"])
    with pytest.raises(ValueError, match=r"failed on the env's observations .*\(4,\)"):
        evaluate(env, policy, 1, exploration=ExplorationType.DETERMINISTIC)


def test_save_lerobot_to_tilde_means_home_not_a_folder_named_tilde(tmp_path, monkeypatch):
    from imitrl.datasets import save_lerobot
    from tests.datasets.test_datasets_faults import _rows

    home = tmp_path / "home"
    home.mkdir()
    (home / ".bashrc").write_text("mine")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=f"{home}|~ exists"):
        save_lerobot(_rows(0), "~", fps=10)
    assert not (tmp_path / "~").exists()
    path = save_lerobot(_rows(0), "~/ds", fps=10)
    assert path == home / "ds" and (home / "ds" / "meta" / "info.json").is_file()


@pytest.mark.parametrize(
    ("label", "message"),
    [(float("nan"), "NaN or inf"), (3.0, r"outside the action bounds \[\[-2.0\], \[2.0\]\]")],
)
def test_rollouts_refuse_nan_or_out_of_bounds_expert_labels(label, message):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=5)
    expert = Expert.from_callable(lambda obs: torch.full((1,), label))
    with pytest.raises(ValueError, match=rf"episode 0, step 0 with \[{label}\], {message}"):
        rollout_episodes(env, expert, 1)


def test_clip_is_the_explicit_way_to_record_clipped_labels():
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=5)
    rows = rollout_episodes(
        env, Expert.from_callable(lambda o: torch.full((1,), 3.0), clip=True), 1
    )
    assert torch.equal(rows[keys.EXPERT_ACTION], torch.full((5, 1), 2.0))
