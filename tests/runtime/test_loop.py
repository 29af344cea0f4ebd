"""The rollout loop's refusals: a policy that cannot act is named for what is wrong."""

from __future__ import annotations

import math

import pytest
import torch

from imitrl.envs import make_env
from imitrl.runtime.loop import policy_errors_named


def test_a_policy_whose_weights_are_nan_is_named_so_not_blamed_on_the_env():
    """A diverged learner's sampling fails inside torch ("probability tensor contains
    either inf, nan"); the message said the policy was built for another env."""
    env = make_env("CartPole-v1", seed=0)
    net = torch.nn.Linear(4, 2)
    with pytest.raises(ValueError, match="another env"):  # finite weights: a shape error
        with policy_errors_named(env, net):
            raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")
    with torch.no_grad():
        net.weight[0, 0] = math.nan
    with pytest.raises(ValueError, match=r"holds weights that are not finite \(NaN or inf") as e:
        with policy_errors_named(env, net):
            raise RuntimeError("probability tensor contains either `inf`, `nan` or element < 0")
    assert "another env" not in str(e.value)
