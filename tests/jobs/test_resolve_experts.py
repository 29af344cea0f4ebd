"""``--expert module:function --expert-kind callable``: the function is called on a batch
``obs [N, *event]`` as its flag promises, whatever the number of lanes (a hostile review:
one lane, the default ``--num-envs 1`` or ``--eval-episodes 1``, handed it one unbatched
observation; the run failed after its fit, and nothing of it was kept)."""

from __future__ import annotations

import json
import sys
import textwrap

import pytest

from imitrl.jobs.resolve import expert_for_env
from tests._cli import run_main

STRICT = textwrap.dedent(
    """
    import torch
    SEEN = []

    def down(obs):  # FrozenLake: integer states [N]
        SEEN.append(tuple(obs.shape))
        assert obs.dim() == 1, obs.shape
        return torch.ones(obs.shape[0], dtype=torch.int64)

    def half(obs):  # MountainCarContinuous: [N, 2] -> [N, 1]
        SEEN.append(tuple(obs.shape))
        assert obs.dim() == 2, obs.shape
        return torch.full((obs.shape[0], 1), 0.5)
    """
)


@pytest.fixture
def strict(tmp_path, monkeypatch):
    (tmp_path / "strict_expert.py").write_text(STRICT)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield __import__("strict_expert")
    sys.modules.pop("strict_expert", None)


@pytest.mark.parametrize(
    ("env", "fn", "extra"),
    [("FrozenLake-v1", "down", []), ("MountainCarContinuous-v0", "half", ["--max-episode-steps", "10"])],
)  # fmt: skip
@pytest.mark.parametrize("lanes", ["1", "2"])
def test_a_callable_expert_is_always_called_on_a_batch(strict, tmp_path, env, fn, extra, lanes):
    status, err = _main("bc", "--env", env, "--expert", f"strict_expert:{fn}", "--expert-kind",
                        "callable", "--num-envs", lanes, "--demos", "2", "--steps", "5",
                        "--eval-episodes", "1", "--no-progress", "--out", str(tmp_path / "o"),
                        *extra)  # fmt: skip
    assert status == 0, err
    assert strict.SEEN and all(len(s) == (1 if fn == "down" else 2) for s in strict.SEEN)
    assert {s[0] for s in strict.SEEN} >= {1}  # one lane's observation, as a batch of one
    status, err = _main("eval", "--expert", f"strict_expert:{fn}", "--expert-kind", "callable",
                        "--env", env, "--eval-episodes", "1", "--no-progress", *extra)  # fmt: skip
    assert status == 0, err


def test_an_expert_that_cannot_label_the_env_says_what_to_pass(strict, tmp_path):
    status, err = _main("bc", "--env", "MountainCarContinuous-v0", "--expert",
                        "strict_expert:down", "--expert-kind", "callable", "--demos", "1",
                        "--no-progress", "--out", str(tmp_path / "o"))  # fmt: skip
    assert status == 2 and "cannot label MountainCarContinuous-v0's observations" in err, err
    assert "; pass --expert module:function" in err and "use pass" not in err
    status, err = _main("bc", "--env", "Taxi-v4", "--expert", "strict_expert:half",
                        "--expert-kind", "callable", "--demos", "1", "--no-progress",
                        "--out", str(tmp_path / "t"))  # fmt: skip
    assert status == 2 and "cannot label Taxi-v4's observations" in err, err
    assert err.rstrip().endswith("use --expert value_iteration"), err


@pytest.mark.parametrize("env", ["FrozenLake-v1", "FrozenLake8x8-v1", "CliffWalking-v1", "Taxi-v4"])
def test_auto_gives_a_toy_text_env_its_value_iteration_expert(env):
    assert expert_for_env("auto", env) == "value_iteration"


def test_frozenlake_bc_runs_with_its_expert_by_default_and_eval_resolves_auto(tmp_path):
    """A hostile review: FrozenLake, the study's env, had no expert for imitrl bc; and
    imitrl eval --expert auto said auto is resolved against --env first."""
    out = tmp_path / "lake"
    status, err = _main("bc", "--env", "FrozenLake-v1", "--env-kwarg", "is_slippery=False",
                        "--demos", "2", "--steps", "50", "--eval-episodes", "2",
                        "--no-progress", "--out", str(out))  # fmt: skip
    assert status == 0, err
    results = json.loads((out / "results.json").read_text())
    assert results["expert"]["mean_return"] == 1.0 and results["expert"]["mean_length"] == 6.0
    status, err = _main("eval", "--expert", "auto", "--env", "FrozenLake-v1", "--env-kwarg",
                        "is_slippery=False", "--eval-episodes", "2", "--no-progress")  # fmt: skip
    assert status == 0, err
    status, err = _main("eval", "--expert", "auto", "--env", "Acrobot-v1", "--eval-episodes", "1",
                        "--no-progress")  # fmt: skip
    assert status == 0, err


def _main(*argv: str) -> tuple[int, str]:
    status, _, err = run_main(*argv)
    return status, err


HOSTILE = textwrap.dedent(
    """
    import torch

    def five(obs):  # CartPole has actions 0 and 1
        return torch.full((obs.shape[0],), 5, dtype=torch.int64)

    def boom():
        raise RuntimeError("boom")

    def leave(obs):
        raise SystemExit(0)
    """
)


@pytest.mark.parametrize(
    ("fn", "kind", "said"),
    [
        ("five", "callable", "the expert's label holds action 5, outside [0, 2)"),
        ("boom", "builder", "--expert hostile_expert:boom: building it raised RuntimeError: boom"),
        ("leave", "callable", "cannot label CartPole-v1's observations (SystemExit: 0)"),
    ],
)
@pytest.mark.parametrize("command", ["bc", "eval", "compare"])
def test_a_users_expert_that_fails_is_one_line_in_every_command(tmp_path, monkeypatch, fn, kind,
                                                                 said, command):  # fmt: skip
    """A hostile review: a label out of range was gymnasium's AssertionError traceback (bc,
    eval, compare), a builder raising was a traceback, an expert calling sys.exit(0) ended
    the command silently with status 0; eval and compare never checked the expert."""
    (tmp_path / "hostile_expert.py").write_text(HOSTILE)
    monkeypatch.syspath_prepend(str(tmp_path))
    argv = {
        "bc": ["bc", "--demos", "1", "--steps", "5", "--no-progress", "--out", str(tmp_path / "o")],
        "eval": ["eval", "--eval-episodes", "1", "--no-progress"],
        "compare": ["compare", "--a", "expert", "--b", "random", "--episodes", "2"],
    }[command]
    status, err = _main(*argv, "--env", "CartPole-v1", "--expert", f"hostile_expert:{fn}",
                        "--expert-kind", kind)  # fmt: skip
    sys.modules.pop("hostile_expert", None)
    assert status == 2 and said in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
