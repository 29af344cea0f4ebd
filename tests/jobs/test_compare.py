"""``imitrl compare`` (issue 47): two checkpoints, or an expert and random actions, on
paired episodes of a gymnasium env and of a Meta-World task; what it prints; bad input
is one line and writes nothing."""

from __future__ import annotations

import json

import pytest

from tests._cli import run_main as _main


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two CartPole checkpoints (a short fit, a long one) and a Pendulum one."""
    root = tmp_path_factory.mktemp("compare")
    for name, env, steps in (("short", "CartPole-v1", "20"), ("long", "CartPole-v1", "600"),
                             ("pend", "Pendulum-v1", "10")):  # fmt: skip
        status, _, err = _main("bc", "--env", env, "--demos", "3", "--steps", steps,
                               "--eval-episodes", "1", "--out", str(root / name),
                               "--no-progress")  # fmt: skip
        assert status == 0, err
    return root


def test_two_checkpoints_on_paired_episodes(runs, tmp_path):
    status, out, err = _main("compare", "--a", str(runs / "short"), "--b", str(runs / "long"),
                             "--episodes", "20", "--out", str(tmp_path / "c"))  # fmt: skip
    assert status == 0, err
    lines = out.splitlines()
    assert "20 paired episodes of at most 500 steps (seeds 10000..10019)" in lines[0]
    assert "difference a - b" in lines[1] and "95% interval" in lines[1]
    saved = json.loads((tmp_path / "c" / "compare.json").read_text())["comparison"]
    assert lines[2] == f"decision: {saved['decision']} ({saved['rule']})"
    assert saved["episodes"] == 20 and saved["metric"] == "return"


def test_a_sequential_comparison_on_a_metaworld_task_stops_early():
    pytest.importorskip("metaworld")
    status, out, err = _main("compare", "--a", "expert", "--b", "random", "--env",
                             "metaworld/reach-v3", "--episodes", "60", "--sequential",
                             "--max-episode-steps", "150")  # fmt: skip
    assert status == 0, err
    assert "success: a 1, b 0" in out and "decision: a better" in out and "stopped early" in out
    used = int(out.split(" paired episodes")[0].rsplit(" ", 1)[1])
    assert used < 60


@pytest.mark.parametrize(
    "argv, said",
    [
        (["--b", "{pend}", "--env", "CartPole-v1"], "(trained on Pendulum-v1) does not fit"),
        (["--b", "{pend}"], "trained on different envs"),
        (["--b", "{long}", "--alpha", "1"], "--alpha must be in [1e-12, 1), got 1"),
        (["--b", "{long}", "--alpha", "0"], "--alpha must be in [1e-12, 1), got 0"),
        (["--b", "{long}", "--alpha", "1e-17"], "--alpha must be in [1e-12, 1), got 1e-17"),
        (["--b", "{long}", "--episodes", "0"], "--episodes must be an integer >= 2"),
        (["--b", "{long}", "--sequential", "--metric", "return"], "--return-range LOW,HIGH"),
        # a hostile review: 0,1e308 overflowed the bets' mapping and the sequential
        # comparison decided for the wrong side; 0,inf played every episode for [-inf, inf]
        (["--b", "random", "--sequential", "--return-range=0,1e308"], "too wide for float64"),
        (["--b", "random", "--sequential", "--return-range=0,inf"], "must be finite"),
        (["--b", "random", "--return-range=-inf,0"], "must be finite"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(runs, tmp_path, argv, said):
    argv = [a.format(pend=runs / "pend", long=runs / "long") for a in argv]
    out = tmp_path / "c"
    status, _, err = _main("compare", "--a", str(runs / "short"), *argv, "--out", str(out))
    assert status == 2 and said in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_a_checkpoint_of_a_dataset_alone_is_compared_in_the_env_named(runs, tmp_path):
    """A checkpoint of ``bc --env none`` (its config names no env) is played in ``--env``,
    as ``imitrl eval --env`` plays it (a hostile review: compare asked for ``--env`` while
    it was given); without ``--env`` it is refused naming the flag."""
    import shutil

    offline = tmp_path / "offline"
    shutil.copytree(runs / "short", offline)
    saved = json.loads((offline / "config.json").read_text())
    saved["config"]["env"] = None  # what bc --env none writes
    (offline / "config.json").write_text(json.dumps(saved))
    status, out, err = _main("compare", "--a", str(offline), "--b", str(runs / "short"),
                             "--env", "CartPole-v1", "--episodes", "4")  # fmt: skip
    assert status == 0, err
    assert "difference a - b +0" in out  # the same weights on the same seeds
    status, _, err = _main("compare", "--a", str(offline), "--b", "random", "--episodes", "4")
    assert status == 2 and "name the env to evaluate it in, --env ENV" in err, err


def test_checkpoints_trained_with_different_env_arguments_are_refused(runs, tmp_path):
    """A hostile review: the first checkpoint's env arguments were played by both sides."""
    import shutil

    other = tmp_path / "other"
    shutil.copytree(runs / "long", other)
    saved = json.loads((other / "config.json").read_text())
    saved["config"]["env_kwargs"] = [["sutton_barto_reward", True]]
    (other / "config.json").write_text(json.dumps(saved))
    status, _, err = _main("compare", "--a", str(runs / "short"), "--b", str(other),
                           "--episodes", "4")  # fmt: skip
    assert status == 2 and "trained with different env arguments" in err, err
    assert "sutton_barto_reward" in err and len(err.strip().splitlines()) == 1
    status, _, err = _main("compare", "--a", str(runs / "short"), "--b", str(other),
                           "--episodes", "4", "--env-kwarg", "sutton_barto_reward=false")  # fmt: skip
    assert status == 0, err


def test_a_checkpoint_against_the_expert_plays_the_checkpoints_env(runs):
    """A review: ``--a CHECKPOINT --b expert`` without ``--env`` was refused, though the
    checkpoint names its env (the help says none means the checkpoint's)."""
    status, out, err = _main("compare", "--a", str(runs / "short"), "--b", "expert",
                             "--episodes", "4")  # fmt: skip
    assert status == 0, err
    assert "4 paired episodes" in out
    status, _, err = _main("compare", "--a", "expert", "--b", "random", "--episodes", "4")
    assert status == 2 and "--env names the env for expert or random" in err


def test_checkpoints_trained_with_different_time_limits_are_refused_and_swap_alike(runs, tmp_path):
    """A hostile review: the first checkpoint's time limit was played by both sides, so
    swapping --a and --b changed the decision."""
    import shutil

    other = tmp_path / "other"
    shutil.copytree(runs / "long", other)
    saved = json.loads((other / "config.json").read_text())
    saved["config"]["max_episode_steps"] = 20
    (other / "config.json").write_text(json.dumps(saved))
    for a, b in ((runs / "short", other), (other, runs / "short")):
        status, _, err = _main("compare", "--a", str(a), "--b", str(b), "--episodes", "4")
        assert status == 2 and "trained with different time limits" in err, err
        assert "--max-episode-steps N" in err
    said = {}
    for a, b in ((runs / "short", other), (other, runs / "short")):
        status, out, err = _main("compare", "--a", str(a), "--b", str(b), "--episodes", "4",
                                 "--max-episode-steps", "30", "--alpha", "0.005")  # fmt: skip
        assert status == 0, err
        assert "of at most 30 steps" in out and "99.5% interval" in out
        said[a == other] = float(out.split("difference a - b ")[1].split(",")[0])
    assert said[True] == -said[False]  # the sides swapped: the difference negated


def test_the_expert_side_is_the_expert_named_by_expert(tmp_path, monkeypatch):
    """A hostile review: compare's expert was the env's built-in one only. On the
    deterministic lake, an expert always moving down falls in the hole at (3, 0) and the
    built-in (value iteration) one reaches the goal; --expert without an expert side is
    refused."""
    (tmp_path / "down_expert.py").write_text(
        "import torch\n\ndef down(obs):\n    return torch.ones(obs.shape[0], dtype=torch.int64)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    lake = ["--env", "FrozenLake-v1", "--env-kwarg", "is_slippery=False", "--episodes", "4"]
    status, out, err = _main("compare", "--a", "expert", "--b", "random", *lake)
    assert status == 0 and "return: a 1, b 0" in out, err
    status, out, err = _main("compare", "--a", "expert", "--b", "random", *lake, "--expert",
                             "down_expert:down", "--expert-kind", "callable")  # fmt: skip
    assert status == 0 and "return: a 0, b 0" in out, err
    status, _, err = _main("compare", "--a", "random", "--b", "random", *lake, "--expert",
                           "down_expert:down")  # fmt: skip
    assert status == 2 and "names the side expert: pass --a or --b expert" in err, err
    status, _, err = _main("compare", "--a", "random", "--b", "random", *lake, "--expert-kind",
                           "junk")  # fmt: skip
    assert status == 2 and "--expert-kind must be one of ('builder', 'callable')" in err, err
    status, _, err = _main("compare", "--a", "expert", "--b", "random", "--env",
                           "CliffWalking-v1", "--episodes", "2")  # fmt: skip
    assert status == 2 and "registered without a time limit: pass --max-episode-steps" in err
