"""Evaluation: unbiased whole-episode Monte Carlo, intervals, exact values beside estimates."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import GymEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.envs import TabularEnv
from imitrl.evaluation import evaluate, mean_ci, tabulate, wilson_interval
from imitrl.experts import cartpole_expert
from imitrl.learners import TaskSpec, build
from imitrl.policies import Expert
from imitrl.tabular import expected_episode_length, success_probability


def test_wilson_interval_known_values():
    lo, hi = wilson_interval(50, 100, 0.95)
    assert lo == pytest.approx(0.4038, abs=1e-4) and hi == pytest.approx(0.5962, abs=1e-4)
    # exactly 0 and 1 at the ends (centre -+ half alone lands 2e-19 inside)
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == 1.0
    assert wilson_interval(0, 1000)[0] == 0.0 and wilson_interval(1000, 1000)[1] == 1.0
    m, lo, hi = mean_ci(torch.tensor([1.0, 2.0, 3.0, 4.0]), 0.95)
    # Student t with 3 degrees of freedom: t_{0.975, 3} = 3.182446 (tables)
    assert m == 2.5 and hi - m == pytest.approx(3.182446 * math.sqrt(5 / 3) / 2, abs=1e-5)
    m, lo, hi = mean_ci(torch.tensor([3.0]))
    assert m == 3.0 and math.isnan(lo) and math.isnan(hi)  # one episode: no interval


@pytest.mark.parametrize("lanes", [1000, 4096])
def test_batched_estimate_agrees_with_exact_value(lake, expert_table, lanes):
    """Whole episodes per lane: no bias toward short episodes, estimate within its 99.9% interval."""
    env = TabularEnv(lake, batch_size=(lanes,), seed=lanes)
    ev = evaluate(
        env,
        Expert.from_table(expert_table).as_actor(),
        20_000,
        exploration=ExplorationType.DETERMINISTIC,
        confidence=0.999,
    )
    exact = success_probability(lake, expert_table)
    assert ev.exact_success == pytest.approx(exact, abs=1e-15)
    assert ev.success_ci[0] < exact < ev.success_ci[1]
    assert ev.mean_return == ev.success_rate  # FrozenLake pays 1 exactly on success
    # mean episode length agrees with the exact expectation (4 standard errors)
    assert abs(ev.mean_length - expected_episode_length(lake, expert_table)) < 4 * 30 / math.sqrt(
        20_000
    )


def test_sampled_policy_has_exact_value_from_its_probabilities(lake):
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))  # uniform random policy
    env = TabularEnv(lake, batch_size=(5000,), seed=3)
    # seeded: unseeded, its draws came from torch's global RNG, set by the tests run before
    ev = evaluate(
        env, learner.policy, 20_000, exploration=ExplorationType.RANDOM, confidence=0.999, seed=3
    )
    probs = tabulate(learner.policy, 16, ExplorationType.RANDOM)
    assert torch.allclose(probs, torch.full((16, 4), 0.25, dtype=torch.float64))
    assert ev.exact_success == pytest.approx(success_probability(lake, probs))
    assert ev.success_ci[0] < ev.exact_success < ev.success_ci[1]
    assert ev.exploration == "random"
    greedy = evaluate(env, learner.policy, 100, exploration=ExplorationType.DETERMINISTIC)
    assert greedy.exact_success == 0.0 and greedy.success_rate == 0.0  # always LEFT never arrives


def test_evaluate_on_a_gym_env():
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    env.set_seed(0)
    ev = evaluate(
        env,
        cartpole_expert().as_actor(),
        3,
        exploration=ExplorationType.DETERMINISTIC,
        max_steps=2000,
    )
    assert ev.mean_return == 500.0 and ev.success_rate is None and ev.exact_success is None
    # the gymnasium TimeLimit (500) ends every episode: no bound needed, and the bare
    # Expert drives the env deterministically without as_actor()
    ev = evaluate(env, cartpole_expert(), 2)
    assert ev.mean_return == 500.0 and ev.mean_length == 500.0 and ev.exploration == "deterministic"
    with pytest.raises(ValueError, match=r"past max_steps=100 steps"):
        evaluate(env, cartpole_expert(), 1, max_steps=100)
    with pytest.raises(ValueError, match="exploration is required"):
        evaluate(env, cartpole_expert().as_actor(), 1)
    with pytest.raises(ValueError, match="num_episodes must be positive"):
        evaluate(
            env,
            cartpole_expert().as_actor(),
            0,
            exploration=ExplorationType.DETERMINISTIC,
            max_steps=10,
        )


def test_exact_values_follow_pinned_lane_starts(lake, expert_table):
    # a quarter of the lanes start next to the goal; 512 lanes: few batched steps for 8000 episodes
    starts = torch.tensor([14, 14, 0, 0, 0, 0, 0, 0]).repeat(64)
    env = TabularEnv(lake, batch_size=(512,), seed=1, initial_state=starts)
    ev = evaluate(
        env,
        Expert.from_table(expert_table).as_actor(),
        8000,
        exploration=ExplorationType.DETERMINISTIC,
        confidence=0.999,
    )
    d0 = torch.zeros(16, dtype=torch.float64)
    d0[14], d0[0] = 0.25, 0.75
    assert ev.exact_success == pytest.approx(
        success_probability(lake, expert_table, initial=d0), abs=1e-12
    )
    assert ev.success_ci[0] < ev.exact_success < ev.success_ci[1]
    with pytest.raises(ValueError, match="pins its lanes"):
        env.play_tables(expert_table, 10)


def test_student_t_quantiles_and_intervals():
    from imitrl.evaluation import student_t_quantile, t_interval

    # reference values of the t distribution's 0.975 quantile
    for df, q in [(1, 12.706204736), (4, 2.776445105), (29, 2.045229642), (200, 1.971896224)]:
        assert student_t_quantile(0.975, df) == pytest.approx(q, abs=1e-6)
    mean, lo, hi = t_interval([1.0, 2.0, 3.0, 4.0, 5.0])
    half = 2.776445105 * math.sqrt(2.5) / math.sqrt(5)
    assert (
        mean == 3.0
        and lo == pytest.approx(3 - half, abs=1e-6)
        and hi == pytest.approx(3 + half, abs=1e-6)
    )
    assert t_interval([2.0])[0] == 2.0 and math.isnan(t_interval([2.0])[1])
    assert math.isnan(t_interval([None])[0])
    with pytest.raises(ValueError, match="df >= 1"):
        student_t_quantile(0.975, 0)


def test_sampled_evaluation_of_trained_and_deterministic_policies(lake, expert_table):
    """float32 probabilities (rows off 1 by ~1e-7) and policies without get_dist are priced exactly."""
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    g = torch.Generator().manual_seed(0)
    states = torch.randint(0, 16, (200,), generator=g)
    fit_bc(
        learner,
        TensorDict({keys.OBSERVATION: states, keys.EXPERT_ACTION: expert_table[states]}, [200]),
        BCConfig(num_steps=30),
    )
    probs = tabulate(learner.policy, 16, ExplorationType.RANDOM)
    assert probs.dtype == torch.float64
    assert torch.allclose(probs.sum(-1), torch.ones(16, dtype=torch.float64), atol=1e-12)
    assert not torch.allclose(probs, torch.full_like(probs, 0.25))  # trained: not exact in float32
    env = TabularEnv(lake, batch_size=(2000,), seed=5)
    ev = evaluate(env, learner.policy, 20_000, exploration=ExplorationType.RANDOM, confidence=0.999)
    assert ev.success_ci[0] < ev.exact_success < ev.success_ci[1]
    # a table-lookup expert has no distribution: sampled = greedy, priced as its table
    ev = evaluate(
        env, Expert.from_table(expert_table).as_actor(), 2000, exploration=ExplorationType.RANDOM
    )
    assert ev.exact_success == pytest.approx(float(success_probability(lake, expert_table)))


def test_sampled_rollouts_follow_an_explicit_generator(lake):
    """RANDOM mode draws from the generator given (same seed, same digits) and leaves the global RNG alone."""
    learner = build(
        "cross_entropy", TaskSpec(action=4, num_states=16)
    )  # uniform: every step samples
    runs = []
    for _ in range(2):
        torch.manual_seed(123)
        before = torch.get_rng_state()
        env = TabularEnv(lake, batch_size=(64,), seed=1)
        ev = evaluate(
            env,
            learner.policy,
            256,
            exploration=ExplorationType.RANDOM,
            generator=torch.Generator().manual_seed(7),
        )
        assert torch.equal(torch.get_rng_state(), before)
        torch.manual_seed(int(torch.randint(0, 1000, ())) + len(runs))  # disturb the global RNG
        runs.append((ev.success_rate, ev.mean_return, ev.mean_length))
    assert runs[0] == runs[1]
    other = evaluate(
        TabularEnv(lake, batch_size=(64,), seed=1),
        learner.policy,
        256,
        exploration=ExplorationType.RANDOM,
        generator=torch.Generator().manual_seed(8),
    )
    assert (other.success_rate, other.mean_return, other.mean_length) != runs[0]


def test_one_episode_has_no_interval_and_policies_must_match_the_action_spec(lake):
    env = TabularEnv(lake, seed=0)
    ev = evaluate(
        env,
        build("cross_entropy", TaskSpec(action=4, num_states=16)).policy,
        1,
        exploration=ExplorationType.DETERMINISTIC,
    )
    assert math.isnan(ev.return_ci[0]) and math.isnan(ev.return_ci[1])
    wide = Expert.from_callable(lambda obs: torch.zeros(*obs.shape, 2, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"needs dtype torch.int64, shape \(\)"):
        evaluate(env, wide.as_actor(), 2, exploration=ExplorationType.DETERMINISTIC)
    with pytest.raises(ValueError, match=r"returned dtype torch.int64, shape \(2,\)"):
        evaluate(env, wide, 2)  # a bare expert is cast to the spec, and refused here
