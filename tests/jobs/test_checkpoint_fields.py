"""A checkpoint's config is data: every field ``imitrl eval`` uses is held to the limits
of its flag, its env arguments never name a file, and weights that are not numbers are
refused (a second hostile review: a downloaded checkpoint's ``xml_file`` made ``imitrl
eval`` open a file outside its folder; ``eval_episodes: 10**12`` asked for 7 TiB; NaN
weights were scored as if they were a policy)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from tests import _watch
from tests._cli import run_main

ENV = "CartPole-v1"


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fields") / "run"
    status, err = _main("bc", "--env", ENV, "--demos", "2", "--steps", "20",
                        "--eval-episodes", "1", "--out", str(out), "--no-progress")  # fmt: skip
    assert status == 0, err
    return out


def _edited(run: Path, where: Path, **fields) -> Path:
    shutil.copytree(run, where)
    saved = json.loads((where / "config.json").read_text())
    saved["config"].update(fields)
    (where / "config.json").write_text(json.dumps(saved))
    return where


@pytest.mark.parametrize(
    "value",
    ["{decoy}", "../outside/model.xml", "./model.xml", "~/model.xml", "assets/x.xml",
     "a\\b.xml", ["fine", "{decoy}"]],
)  # fmt: skip
def test_env_arguments_naming_a_file_are_refused_before_the_env_is_made(run, tmp_path, value):
    outside = tmp_path / "outside"
    outside.mkdir()
    decoy = outside / "model.xml"
    decoy.write_text("<mujoco/>")
    value = [v.format(decoy=decoy) for v in value] if isinstance(value, list) else value
    value = value.format(decoy=decoy) if isinstance(value, str) else value
    bad = _edited(run, tmp_path / "bad", env_kwargs=[["xml_file", value]])
    with _watch.Watch(outside) as watch:
        status, err = _main("eval", "--checkpoint", str(bad), "--eval-episodes", "1")
        touched = watch.events()
    assert status == 2 and "env_kwargs xml_file=" in err and "names a file" in err, err
    assert "--env-kwarg xml_file=" in err and len(err.strip().splitlines()) == 1
    assert touched == []
    # the command's own arguments go over the checkpoint's: the saved file would still
    # be opened, so it is still refused (only --env-kwarg xml_file=... replaces it)
    status, err = _main("eval", "--checkpoint", str(bad), "--eval-episodes", "1",
                        "--env-kwarg", "sutton_barto_reward=false")  # fmt: skip
    assert status == 2 and "names a file" in err, err


def test_env_arguments_that_name_no_file_are_played(run, tmp_path):
    fine = _edited(run, tmp_path / "fine", env_kwargs=[["sutton_barto_reward", True]])
    status, err = _main("eval", "--checkpoint", str(fine), "--eval-episodes", "1")
    assert status == 0, err


@pytest.mark.parametrize(
    ("field", "value", "said"),
    [
        ("eval_episodes", 10**12, "eval_episodes must be"),
        ("eval_episodes", 0, "eval_episodes must be an integer >= 1"),
        ("eval_episodes", "x", "eval_episodes must be"),
        ("eval_seed", -1, "eval_seed must be an integer >= 0"),
        ("eval_seed", 2**80, "eval_seed must be"),
        ("eval_seed", 1.5, "eval_seed must be"),
    ],
)
def test_evaluation_fields_are_held_to_their_flags_limits(run, tmp_path, field, value, said):
    bad = _edited(run, tmp_path / "bad", **{field: value})
    status, err = _main("eval", "--checkpoint", str(bad))
    assert status == 2 and said in err and "config.json" in err, err
    assert len(err.strip().splitlines()) == 1


def test_null_evaluation_fields_take_the_defaults(run, tmp_path):
    old = _edited(run, tmp_path / "old", eval_episodes=None, eval_seed=None)
    status, err = _main("eval", "--checkpoint", str(old), "--eval-episodes", "1")
    assert status == 0, err


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_weights_that_are_not_numbers_are_refused(run, tmp_path, value):
    bad = tmp_path / "nan"
    shutil.copytree(run, bad)
    state = torch.load(bad / "learner.pt", weights_only=True)
    name = "policy.module.0.module.5.weight"  # the output layer's weights
    state[name] = torch.full_like(state[name], value)
    torch.save(state, bad / "learner.pt")
    status, err = _main("eval", "--checkpoint", str(bad), "--eval-episodes", "1")
    assert status == 2 and f"{name!r} holds NaN or inf" in err and "learner.pt" in err, err


def test_a_checkpoint_evaluated_in_another_env_is_one_line_naming_its_env(run):
    """Was torch's list of every mismatched weight, 16 lines."""
    status, err = _main("eval", "--checkpoint", str(run), "--env", "Acrobot-v1",
                        "--eval-episodes", "1")  # fmt: skip
    assert status == 2 and "the checkpoint was trained on CartPole-v1" in err, err
    assert "size mismatch" not in err and len(err.strip().splitlines()) == 1


def _main(*argv: str) -> tuple[int, str]:
    status, _, err = run_main(*argv)
    return status, err


@pytest.mark.parametrize("value", [0.0, -1.0])
def test_a_normaliser_scale_fit_never_writes_is_refused(run, tmp_path, value):
    """A hostile review: a scale edited to 0 was scored on inf inputs (NaN weights were
    refused); a fitted scale is a standard deviation >= min_scale, or 1."""
    bad = tmp_path / "scale"
    shutil.copytree(run, bad)
    state = torch.load(bad / "learner.pt", weights_only=True)
    names = [k for k in state if k.endswith("normalizer.scale")]
    assert names, sorted(state)
    # every copy of that one weight (the policy's and its loss's too): copies that
    # disagree are refused for that reason first (Learner.load_state_dict)
    names = [k for k in state if k.endswith("scale") and torch.equal(state[k], state[names[0]])]
    for name in names:
        state[name] = torch.full_like(state[name], value)
    torch.save(state, bad / "learner.pt")
    status, err = _main("eval", "--checkpoint", str(bad), "--eval-episodes", "1")
    assert status == 2 and "a normaliser's scale is a standard deviation" in err, err
    status, err = _main("eval", "--checkpoint", str(run), "--eval-episodes", "1")
    assert status == 0, err  # the checkpoint as saved
