"""Episodes, not step budgets: the env's own time limit, per-episode bounds, seeded initial states."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs import GymWrapper, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import EnvSource
from imitrl.compat import wrapped_gym_env
from imitrl.envs import TabularEnv, episode_limit, make_env
from imitrl.envs.multimodal import TwoWayObstacleEnv, two_way_expert
from imitrl.evaluation import evaluate
from imitrl.experts import pendulum_expert
from imitrl.learners import TaskSpec, build
from imitrl.policies import Expert
from imitrl.runtime import episode_returns, rollout_episodes

RANDOM = ExplorationType.RANDOM


def _endless_pendulum() -> GymWrapper:
    """Pendulum without its TimeLimit: it never ends an episode by itself."""
    return GymWrapper(gymnasium.make("Pendulum-v1").unwrapped)


def _still() -> Expert:
    """Zero torque (float64 numpy, cast to the env's float32 [1])."""
    return Expert.from_callable(lambda obs: np.zeros(obs.shape[:-1]))


# ------------------------------------------------------------------ episode_limit
def test_episode_limit_finds_every_kind_of_time_limit(lake):
    assert episode_limit(make_env("CartPole-v1", seed=0)) == 500
    assert episode_limit(make_env("CartPole-v1", seed=0, max_episode_steps=33)) == 33
    assert episode_limit(make_env("CartPole-v1", seed=0, num_envs=3)) == 500
    assert episode_limit(make_env("Pendulum-v1", seed=0)) == 200
    assert episode_limit(make_env("Pendulum-v1", seed=0, frame_skip=3)) == 67  # ceil(200 / 3)
    assert (
        episode_limit(TabularEnv(lake)) == 100
        and episode_limit(TabularEnv(lake, max_steps=None)) is None
    )
    assert episode_limit(TwoWayObstacleEnv()) is None
    assert episode_limit(_endless_pendulum()) is None
    counted = TransformedEnv(_endless_pendulum(), StepCounter(max_steps=7))
    assert episode_limit(counted) == 7
    both = TransformedEnv(make_env("CartPole-v1", seed=0), StepCounter(max_steps=900))
    assert episode_limit(both) == 500  # the smaller limit ends the episode


def test_episode_limit_of_a_parallel_env():
    env = make_env("CartPole-v1", seed=0, num_envs=2, parallel=True, max_episode_steps=40)
    assert episode_limit(env) == 40


def test_the_private_gym_access_matches_the_public_forwarding():
    env = make_env("CartPole-v1", seed=0, max_episode_steps=21)
    assert wrapped_gym_env(env).spec == env.spec  # GymWrapper.__getattr__ forwards `spec`
    assert env.spec.max_episode_steps == 21


# ------------------------------------------------------------------- per episode
def test_an_env_without_a_limit_needs_max_steps_up_front():
    env = _endless_pendulum()
    with pytest.raises(ValueError, match=r"GymWrapper has no time limit .* pass max_steps="):
        rollout_episodes(env, _still(), 1)
    with pytest.raises(ValueError, match="pass max_steps="):
        evaluate(env, _still(), 1)
    with pytest.raises(ValueError, match=r"EnvSource\(env, max_steps=...\)"):
        EnvSource(env)
    # the policy never ends an episode: the per-episode bound is named
    with pytest.raises(ValueError, match=r"ran past max_steps=25 steps"):
        rollout_episodes(env, _still(), 1, max_steps=25)
    with pytest.raises(ValueError, match=r"ran past max_steps=25 steps"):
        EnvSource(env, max_steps=25).collect(_still(), 1, round_index=0, first_episode=0)


def test_max_steps_bounds_each_episode_not_a_lane_total():
    # 30-step episodes, 4 per lane: 120 steps per lane under a bound of 30 per episode
    env = TransformedEnv(_endless_pendulum(), StepCounter(max_steps=30))
    rows = rollout_episodes(env, _still(), 4, max_steps=30)
    assert rows.shape[0] == 120 and int(rows[keys.STEP].max()) == 29
    summary = episode_returns(env, _still(), 4, max_steps=30)
    assert summary.lengths.tolist() == [30, 30, 30, 30]
    with pytest.raises(ValueError, match=r"ran past max_steps=29"):
        episode_returns(env, _still(), 1, max_steps=29)


def test_a_time_limited_env_needs_no_bound(lake):
    env = make_env("Pendulum-v1", seed=0, num_envs=2)
    summary = episode_returns(env, pendulum_expert(), 3)
    assert summary.lengths.tolist() == [200, 200, 200]
    rows = rollout_episodes(
        TabularEnv(lake, batch_size=(8,), seed=0), Expert.from_q(torch.eye(16, 4)), 40
    )
    assert int(rows[keys.EPISODE].unique().numel()) == 40
    assert (
        EnvSource(env).collect(pendulum_expert(), 1, round_index=0, first_episode=0).shape[0] == 200
    )


# ------------------------------------------------------------------ same initial states
def _starts(env, policy, n, **kw):
    rows = rollout_episodes(env, policy, n, max_steps=100, **kw)
    return rows[rows[keys.STEP] == 0][keys.OBSERVATION]


def test_a_seed_gives_two_policies_the_same_initial_states():
    env = TwoWayObstacleEnv(batch_size=(8,), seed=0)
    first = _starts(env, two_way_expert(), 8, seed=3)
    second = _starts(env, _still(), 8, seed=3)  # a different policy, no hand-called set_seed
    assert torch.equal(first, second)
    assert not torch.equal(_starts(env, _still(), 8), first)  # no seed: the env's stream goes on
    gym = make_env("Pendulum-v1", seed=0)
    a = rollout_episodes(gym, pendulum_expert(), 1, seed=11)[keys.OBSERVATION][0]
    b = rollout_episodes(gym, _still(), 1, seed=11)[keys.OBSERVATION][0]
    c = rollout_episodes(gym, _still(), 1)[keys.OBSERVATION][0]
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_evaluate_with_a_seed_repeats_its_digits(lake, expert_table):
    env = TabularEnv(lake, batch_size=(16,), seed=0)
    expert = Expert.from_table(expert_table)
    runs = [evaluate(env, expert, 64, seed=5) for _ in range(2)]
    assert runs[0] == runs[1]
    assert evaluate(env, expert, 64) != evaluate(env, expert, 64)  # the env's stream goes on
    learner = build(
        "cross_entropy", TaskSpec(action=4, num_states=16)
    )  # uniform: every step samples
    sampled = [evaluate(env, learner, 64, exploration=RANDOM, seed=9) for _ in range(2)]
    assert sampled[0] == sampled[1]
    assert sampled[0] != evaluate(env, learner, 64, exploration=RANDOM, seed=10)
