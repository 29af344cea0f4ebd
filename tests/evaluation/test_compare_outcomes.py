"""What a comparison refuses to decide on (a hostile review): equal differences at a level
two pairs cannot reach, returns outside ``return_range`` (were clipped, and could reverse
the sign), and outcomes that are not numbers."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType

from imitrl.envs import make_env
from imitrl.evaluation.compare import PolicySpec, betting_interval, compare
from tests.evaluation.test_compare import _sides


def _sutton_barto():
    """CartPole paying -1 at a fall and 0 otherwise: in 100 steps the expert never falls
    and random actions always do, so every paired difference is +1."""
    return make_env("CartPole-v1", seed=0, max_episode_steps=100,
                    env_kwargs={"sutton_barto_reward": True})  # fmt: skip


def test_equal_differences_get_the_bounded_outcomes_betting_interval():
    """Every difference the same: a t-interval (or the sign-flip test's, used before) is
    that value alone, which held only for differences symmetric about their mean (a
    hostile review: 0/1 outcomes tied in 20 of 20 pairs missed a true -0.05 in 36% of
    draws). With bounds, the betting interval, valid for any distribution in them; returns
    without bounds allow any mean."""
    env = _sutton_barto()
    a, b = _sides(env)
    free = compare(env, a, b, 21, alpha=1e-6, metric="return")
    assert free.difference == 1.0 and free.decision == "no difference shown"
    assert free.interval == (-math.inf, math.inf) and "without bounds" in free.rule
    assert free.as_dict()["interval"] == [None, None]  # JSON has no infinity
    two = compare(env, a, b, 2, alpha=0.05, metric="return", return_range=(-1.0, 0.0))
    assert two.decision == "no difference shown" and two.interval[1] == 1.0
    many = compare(env, a, b, 40, alpha=0.05, metric="return", return_range=(-1.0, 0.0))
    assert many.rule == "fixed: hedged betting interval (every difference equal)"
    assert 0.0 < many.interval[0] < 1.0 == many.interval[1] and many.decision == "a better"
    assert many.interval == betting_interval(torch.ones(40, dtype=torch.float64), 0.05, (-1.0, 0.0))


@pytest.mark.parametrize("sequential", [False, True])
def test_a_return_outside_the_stated_range_is_refused_not_clipped(sequential):
    env = make_env("CartPole-v1", seed=0, max_episode_steps=50)
    a, b = _sides(env)
    with pytest.raises(ValueError, match=r"expert's episode 0 \(seed 3\) returned 50, outside "
                                         r"the return range \[0, 5\]"):  # fmt: skip
        compare(env, a, b, 30, seed=3, metric="return", return_range=(0.0, 5.0),
                sequential=sequential)  # fmt: skip


def test_outcomes_that_are_not_numbers_are_refused_naming_the_episode():
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=5)
    nan = TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 1), math.nan),
                           in_keys=["observation"], out_keys=["action"])  # fmt: skip
    a = PolicySpec(nan, ExplorationType.DETERMINISTIC, "broken")
    b = PolicySpec(nan, ExplorationType.DETERMINISTIC, "other")
    with pytest.raises(ValueError, match=r"broken's episode 0 \(seed 0\) has a return of nan"):
        compare(env, a, b, 3, metric="return")
