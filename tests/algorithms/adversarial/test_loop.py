"""The adversarial loop's rounds: a round that goes non-finite is one line naming it."""

from __future__ import annotations

import math

import pytest
import torch

from imitrl.algorithms.adversarial.loop import RoundRecord, check_finite_round
from tests._cli import run_main


def _record(**changes) -> RoundRecord:
    base = dict(
        round=3,
        env_steps=100,
        discriminator={"loss": 0.7, "grad_penalty": 0.0},
        generator={"loss_objective": 0.1, "loss_critic": 2.0},
        learned_reward=0.5,
    )
    return RoundRecord(**{**base, **changes})


@pytest.mark.parametrize(
    ("changes", "named"),
    [
        ({"discriminator": {"loss": math.nan}}, "the discriminator's loss"),
        ({"generator": {"loss_objective": 0.1, "loss_critic": math.inf}}, "PPO's loss_critic"),
        ({"learned_reward": -math.inf}, "the learned reward"),
    ],
)
def test_a_round_whose_numbers_are_not_finite_is_named(changes, named):
    with pytest.raises(ValueError, match=f"round 3: {named} is not finite: training diverged"):
        check_finite_round(_record(**changes), [torch.zeros(2)])


def test_a_round_that_leaves_a_weight_nan_is_named():
    check_finite_round(_record(), [torch.zeros(2), torch.ones(3)])  # finite: nothing said
    with pytest.raises(ValueError, match="round 3: the learner's weights is not finite"):
        check_finite_round(_record(), [torch.zeros(2), torch.tensor([1.0, math.nan])])


def test_a_rollout_leaving_one_row_for_the_last_minibatch_trains_finite(tmp_path):
    """65 rows in minibatches of 64: the last holds one row, whose advantage TorchRL leaves
    unnormalised; the accelerated step divided it by a NaN std, every weight went NaN and
    the run reported success with exit 0."""
    out = tmp_path / "g"
    status, _, err = run_main(
        "gail", "--env", "CartPole-v1", "--demos", "1", "--eval-episodes", "1",
        "--ppo-epochs", "1", "--total-steps", "65", "--rollout-steps", "65",
        "--minibatch-size", "64", "--no-progress", "--out", str(out),
    )  # fmt: skip
    assert status == 0, err
    state = torch.load(out / "learner.pt", weights_only=True)
    floats = [v for v in state.values() if torch.is_tensor(v) and v.is_floating_point()]
    assert floats and all(bool(torch.isfinite(v).all()) for v in floats)
