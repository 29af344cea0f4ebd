"""Malformed inputs raise ValueError naming the problem."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from imitrl.tabular import TabularMDP, policy_probs, success_probability


def _good():
    P = np.full((3, 2, 3), 1 / 3)
    r = np.zeros((3, 2))
    return P, r


def test_rows_not_summing_to_one():
    P, r = _good()
    P[1, 0, 2] = 0.5
    with pytest.raises(ValueError, match=r"sum to 1.*\(1, 0\)"):
        TabularMDP.from_arrays(P, r, 0.9)


def test_negative_probability():
    P, r = _good()
    P[2, 1] = [1.2, -0.2, 0.0]
    with pytest.raises(ValueError, match="negative probability"):
        TabularMDP.from_arrays(P, r, 0.9)


@pytest.mark.parametrize(
    ("P_shape", "r_shape", "match"),
    [
        ((3, 2, 4), (3, 2), r"P must have shape \[S, A, S\]"),
        ((3, 2, 3), (2, 3), "r must have shape"),
        ((3, 3), (3, 2), "P must have shape"),
    ],
)
def test_shape_mismatch(P_shape, r_shape, match):
    P = np.full(P_shape, 1.0 / P_shape[-1])
    with pytest.raises(ValueError, match=match):
        TabularMDP.from_arrays(P, np.zeros(r_shape), 0.9)


def test_non_finite_values():
    P, r = _good()
    r[0, 0] = np.nan
    with pytest.raises(ValueError, match="r must be finite"):
        TabularMDP.from_arrays(P, r, 0.9)
    P2, r2 = _good()
    P2[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="P must be finite"):
        TabularMDP.from_arrays(P2, r2, 0.9)


def test_bad_gamma_initial_and_terminal():
    P, r = _good()
    with pytest.raises(ValueError, match="gamma"):
        TabularMDP.from_arrays(P, r, 1.5)
    with pytest.raises(ValueError, match="initial distribution rows must sum to 1"):
        TabularMDP.from_arrays(P, r, 0.9, initial=[0.5, 0.2, 0.2])
    with pytest.raises(ValueError, match="terminal must be a bool array"):
        TabularMDP.from_arrays(P, r, 0.9, terminal=[0, 1, 0])


def test_env_without_tabular_model():
    with pytest.raises(ValueError, match="no tabular model"):
        TabularMDP.from_gym("CartPole-v1", 0.9)


def test_unknown_env_id():
    with pytest.raises(ValueError, match="unknown or unbuildable gymnasium env id 'NoSuchLake-v9'"):
        TabularMDP.from_gym("NoSuchLake-v9", 0.9)


class _BadModelEnv(gym.Env):
    """A toy-text-like env whose model has a row summing to 0.9."""

    observation_space = gym.spaces.Discrete(2)
    action_space = gym.spaces.Discrete(1)
    initial_state_distrib = np.array([1.0, 0.0])

    def __init__(self, model):
        self.P = model


def test_gym_model_rows_checked():
    env = _BadModelEnv({0: {0: [(0.9, 1, 0.0, True)]}, 1: {0: [(1.0, 1, 0.0, True)]}})
    with pytest.raises(ValueError, match=r"P\[0\]\[0\] sum to 0.9"):
        TabularMDP.from_gym(env, 0.9)
    env = _BadModelEnv({0: {0: [(1.0, 5, 0.0, True)]}, 1: {0: [(1.0, 1, 0.0, True)]}})
    with pytest.raises(ValueError, match="next state 5 outside"):
        TabularMDP.from_gym(env, 0.9)
    env = _BadModelEnv({0: {0: [(1.0, 1, 0.0, True)]}})
    with pytest.raises(ValueError, match="no entry for state 1"):
        TabularMDP.from_gym(env, 0.9)


def test_state_dependent_termination_is_required():
    # state 1 is entered once with terminated=True and once without
    model = {
        0: {0: [(0.5, 1, 0.0, True), (0.5, 2, 0.0, False)]},
        1: {0: [(1.0, 1, 0.0, True)]},
        2: {0: [(1.0, 1, 0.0, False)]},
    }
    env = _BadModelEnv(model)
    env.observation_space = gym.spaces.Discrete(3)
    env.initial_state_distrib = np.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="termination is not a function of the next state"):
        TabularMDP.from_gym(env, 0.9)


def test_policy_validation(lake):
    with pytest.raises(ValueError, match=r"action 4 at state 3 is outside \[0, 4\)"):
        success_probability(lake, torch.tensor([0, 0, 0, 4] + [0] * 12))
    with pytest.raises(ValueError, match="must have shape"):
        policy_probs(torch.zeros(15, dtype=torch.long), 16, 4)
    with pytest.raises(ValueError, match="integer actions"):
        policy_probs(torch.zeros(16), 16, 4)
    rows = torch.full((16, 4), 0.3)
    with pytest.raises(ValueError, match="sum to"):
        policy_probs(rows, 16, 4)


def test_a_model_too_large_for_a_dense_kernel_is_refused_before_it_is_read():
    """A hostile review: a 66x66 lake (``--env-kwarg desc=...``, the study's ``--desc``)
    asked for a dense 4356 x 4 x 4356 kernel; twice as wide, more memory than the machine."""
    from gymnasium.envs.toy_text.frozen_lake import generate_random_map

    desc = generate_random_map(66, seed=0)
    with pytest.raises(ValueError, match=r"4356 states and 4 actions.*MAX_KERNEL_ENTRIES"):
        TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs={"desc": desc})
    small = TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs={"desc": desc[:8]})
    assert small.num_states == 8 * 66
