"""imitrl gail / airl: refusals that name the flags, before anything is evaluated."""

from __future__ import annotations

from tests._cli import run_main

TINY = ["--demos", "1", "--eval-episodes", "1", "--ppo-epochs", "1", "--total-steps", "64",
        "--rollout-steps", "64", "--no-progress"]  # fmt: skip


def test_gamma_1_with_absorbing_states_names_the_flags_before_evaluating(tmp_path):
    """Acrobot's demonstrations terminate, so absorbing states are on; with --gamma 1 the
    run was refused after the expert's and the learner's evaluations, naming
    ``absorbing=False`` (a Python argument) for the CLI's --no-absorbing."""
    status, out, err = run_main(
        "gail", "--env", "Acrobot-v1", "--gamma", "1", *TINY, "--out", str(tmp_path / "g")
    )
    assert status == 2, err
    assert "--gamma 1 with absorbing states (on: the demonstrations terminate)" in err
    assert "--no-absorbing" in err and "absorbing=False" not in err
    assert "expert:" not in out  # nothing was evaluated first


def test_a_loss_without_a_value_head_is_named_before_its_learning_rate(tmp_path):
    """``--loss act`` said "leave --lr out" though --lr was never given (GAIL's default);
    the reason it cannot run at all came only after --lr 0.003."""
    status, _, err = run_main(
        "gail", "--env", "Pendulum-v1", "--loss", "act", *TINY, "--out", str(tmp_path / "g")
    )
    assert status == 2 and "builds no value head" in err and "leave lr out" not in err, err


def test_gamma_1_with_absorbing_asked_for_names_the_flag(tmp_path):
    status, _, err = run_main(
        "gail", "--env", "Pendulum-v1", "--absorbing", "--gamma", "1", *TINY,
        "--out", str(tmp_path / "g"),
    )  # fmt: skip
    assert status == 2 and "--no-absorbing" in err, err
