"""Paired comparisons (issue 47): both sides play episode j from the same seed; the fixed
rule is the paired t interval; the sequential rule's confidence sequence covers the true
mean difference and stops early when the difference is large; an env that does not
replay its seeds is refused."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs.utils import ExplorationType

from imitrl.envs import make_env
from imitrl.evaluation.compare import PolicySpec, betting_interval, check_replays, compare
from imitrl.evaluation.statistics import t_interval
from imitrl.experts import cartpole_expert
from imitrl.policies.random_actions import RandomActions


def _sides(env):
    expert = cartpole_expert()
    expert.bind(env.action_spec_unbatched)
    a = PolicySpec(expert.as_actor(), ExplorationType.DETERMINISTIC, "expert")
    b = PolicySpec(RandomActions(env.action_spec_unbatched), ExplorationType.RANDOM, "random")
    return a, b


def test_a_fixed_comparison_is_the_paired_t_interval_of_seeded_episodes():
    env = make_env("CartPole-v1", seed=0)
    a, b = _sides(env)
    got = compare(env, a, b, 12, seed=7, metric="return")
    assert got.episodes == 12 and got.decision == "a better" and not got.stopped_early
    # episode j is seeded 7 + j whatever the lanes: a greedy side's outcomes are the same
    # from a 3-lane env (a sampling side draws for its lanes at once: not its digits)
    lanes = make_env("CartPole-v1", seed=0, num_envs=3)
    a3, _ = _sides(lanes)
    again = compare(lanes, a3, a3, 12, seed=7, metric="return")
    assert again.mean_a == got.mean_a and again.difference == 0.0
    # by hand: random actions alone, episode j from seed 7 + j
    from imitrl.runtime.returns import episode_returns

    one = make_env("CartPole-v1", seed=0)
    xb = [float(episode_returns(one, b.policy, 1, exploration=b.exploration, seed=7 + j)
                .returns[0]) for j in range(12)]  # fmt: skip
    assert got.mean_b == pytest.approx(sum(xb) / 12, abs=1e-12)
    mean, lo, hi = t_interval([500.0 - x for x in xb], 0.95)
    assert got.interval == pytest.approx((lo, hi)) and got.difference == pytest.approx(mean)


def test_a_policy_against_itself_on_paired_episodes_differs_by_nothing():
    env = make_env("CartPole-v1", seed=0)
    _, b = _sides(env)
    got = compare(env, b, b, 10, metric="return")
    assert got.difference == 0.0 and got.decision == "no difference shown"


def test_the_sequential_rule_stops_early_on_a_large_difference():
    env = make_env("CartPole-v1", seed=0)
    a, b = _sides(env)
    got = compare(env, a, b, 200, sequential=True, return_range=(0.0, 500.0))
    assert got.stopped_early and got.episodes < 40 and got.decision == "a better"
    lo, hi = got.interval
    assert lo > 0 and lo <= got.difference <= hi


def test_the_confidence_sequence_covers_at_its_level_at_every_stop():
    """Bernoulli(0.6) - Bernoulli(0.45) pairs: over 200 sequences of 200, the running
    interval excludes the true difference 0.15 at some point in at most about alpha of
    them (Ville's inequality bounds it by alpha; binomial slack 3 sd)."""
    g = torch.Generator().manual_seed(0)
    misses = 0
    runs, n, alpha = 200, 200, 0.1
    for _ in range(runs):
        d = (torch.rand(n, generator=g) < 0.6).double() - (
            torch.rand(n, generator=g) < 0.45
        ).double()
        for t in (20, 50, 100, 200):  # a few stopping times of the same sequence
            lo, hi = betting_interval(d[:t], alpha, (0.0, 1.0))
            if not lo <= 0.15 <= hi:
                misses += 1
                break
    assert misses / runs <= alpha + 3 * (alpha * (1 - alpha) / runs) ** 0.5


class _Unseeded(gymnasium.Env):
    """Resets to a point drawn from numpy's global generator: no seed replays it."""

    observation_space = gymnasium.spaces.Box(-1, 1, (1,), np.float32)
    action_space = gymnasium.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        return np.random.uniform(-1, 1, (1,)).astype(np.float32), {}  # noqa: NPY002

    def step(self, action):
        return np.zeros(1, np.float32), 0.0, True, False, {}


def test_an_env_that_does_not_replay_its_seeds_is_refused():
    from torchrl.envs import GymWrapper

    env = GymWrapper(_Unseeded())
    with pytest.raises(ValueError, match="does not replay its episodes from a seed"):
        check_replays(env, 3)


def test_an_env_on_envbase_seeded_by_set_seed_replays():
    """The two-way task keeps its own generator, which ``set_seed`` reseeds and TorchRL's
    ``reset(seed=...)`` does not reach: it replays as the paired episodes seed it."""
    from imitrl.envs.multimodal import TwoWayObstacleEnv

    env = TwoWayObstacleEnv(seed=0, batch_size=(4,))
    env.rollout(10, break_when_any_done=False)  # its generator moved on
    check_replays(env, 3)


@pytest.mark.parametrize(
    "kwargs, said",
    [({"alpha": 1.0}, "alpha must be in"), ({"alpha": 0.0}, "alpha must be in"),
     ({"episodes": 1}, "episodes must be an integer >= 2"),
     ({"sequential": True, "metric": "return"}, "needs their bounds"),
     ({"metric": "success"}, "reports no success")],
)  # fmt: skip
def test_bad_requests_are_one_line(kwargs, said):
    env = make_env("CartPole-v1", seed=0)
    a, b = _sides(env)
    args = {"episodes": 10, **kwargs}
    with pytest.raises(ValueError, match=said):
        compare(env, a, b, args.pop("episodes"), **args)


def test_a_betting_interval_reaches_the_bound_its_outcomes_sit_on():
    """Differences all at +span (a always succeeds, b always fails): the truth, +span, is
    in the interval (a hostile review: the grid leaves out its ends, and the interval
    stopped at 0.999); an interval away from the bounds keeps its grid points."""
    ones = torch.ones(100, dtype=torch.float64)
    low, high = betting_interval(ones, 0.05, (0.0, 1.0))
    assert high == 1.0 and 0.5 < low < 1.0
    assert betting_interval(-ones, 0.05, (0.0, 1.0))[0] == -1.0
    mixed = torch.tensor([1.0, 0.0, -1.0, 0.0] * 25, dtype=torch.float64)
    low, high = betting_interval(mixed, 0.05, (0.0, 1.0))
    assert -1.0 < low < 0.0 < high < 1.0


@pytest.mark.parametrize(
    ("bounds", "said"),
    [((0.0, 1e308), "too wide for float64"), ((0.0, float("inf")), "must be finite"),
     ((float("nan"), 1.0), "must be finite"), ((1.0, 1.0), "low < high")],
)  # fmt: skip
def test_a_return_range_the_bets_cannot_use_is_refused(bounds, said):
    env = make_env("CartPole-v1", seed=0, max_episode_steps=20)
    expert = PolicySpec(cartpole_expert().as_actor(), ExplorationType.DETERMINISTIC, "expert")
    with pytest.raises(ValueError, match=said):
        compare(env, expert, expert, 4, metric="return", return_range=bounds, sequential=True)
