"""Exact math of the tabular toolkit: known values, closed forms, hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from imitrl.tabular import (
    TabularMDP,
    expected_episode_length,
    expected_return,
    greedy,
    occupancy,
    policy_evaluation,
    reachable_states,
    state_distributions,
    success_probability,
    total_variation,
    value_iteration,
)

SEED_EXPERT = [0, 3, 0, 3, 0, 0, 0, 0, 3, 1, 0, 0, 0, 2, 1, 0]


def test_frozenlake_value_iteration_policy_and_value(lake, expert_table):
    V = value_iteration(lake, 1000)[-1]
    assert expert_table.tolist() == SEED_EXPERT
    assert round(float(V[0]), 6) == 0.180472


def test_frozenlake_expert_success_within_time_limit_and_without(lake, expert_table):
    assert lake.max_steps == 100
    assert round(success_probability(lake, expert_table), 6) == 0.729766
    assert success_probability(lake, expert_table, math.inf) == pytest.approx(32 / 41, abs=1e-12)


def test_value_iteration_history_shape_and_start(lake):
    H = value_iteration(lake, 7)
    assert H.shape == (7, 16) and H.dtype == torch.float64
    assert torch.equal(H[0], lake.r.max(dim=1).values)  # V_1 = max_a r(s, a) from V_0 = 0
    # monotone from V_0 = 0 with non-negative rewards
    assert (H[1:] >= H[:-1] - 1e-15).all()
    with pytest.raises(ValueError, match="positive integer"):
        value_iteration(lake, 0)


def test_policy_evaluation_matches_value_iteration_fixed_point(lake, expert_table):
    V_star = value_iteration(lake, 2000)[-1]
    V_pi = policy_evaluation(lake, expert_table)
    assert torch.allclose(V_pi, V_star, atol=1e-12)


def test_undiscounted_evaluation_is_the_absorption_probability(lake, expert_table):
    V = policy_evaluation(lake.with_gamma(1.0), expert_table)
    assert float(V[0]) == pytest.approx(32 / 41, abs=1e-12)


def test_undiscounted_evaluation_rejects_non_terminating_policy():
    # two states that swap forever, no terminal state
    P = np.zeros((2, 1, 2))
    P[0, 0, 1] = P[1, 0, 0] = 1.0
    mdp = TabularMDP.from_arrays(P, np.zeros((2, 1)), 1.0)
    with pytest.raises(ValueError, match="terminate"):
        policy_evaluation(mdp, torch.zeros(2, dtype=torch.long))


def test_greedy_ties_go_to_the_lowest_action():
    Q = torch.tensor([[1.0, 1.0, 0.0], [0.0, 2.0, 2.0], [3.0, 3.0, 3.0]], dtype=torch.float64)
    assert greedy(Q).tolist() == [0, 1, 0]


def _coin_mdp(p: float = 0.5) -> TabularMDP:
    """State 0 moves to terminal state 1 with probability p (reward 1 on entry), else stays."""
    P = np.zeros((2, 1, 2))
    P[0, 0] = [1 - p, p]
    P[1, 0, 1] = 1.0
    R = np.zeros((2, 1, 2))
    R[0, 0, 1] = 1.0
    return TabularMDP.from_arrays(P, R, 0.9, terminal=[False, True])


def test_hand_computed_coin_mdp():
    mdp = _coin_mdp(0.5)
    pi = torch.zeros(2, dtype=torch.long)
    for T in (0, 1, 2, 5, 10):
        assert success_probability(mdp, pi, T) == pytest.approx(1 - 0.5**T, abs=1e-15)
        assert expected_return(mdp, pi, T) == pytest.approx(1 - 0.5**T, abs=1e-15)
        # E[min(Geometric(1/2), T)] = sum_{t<T} 0.5^t
        assert expected_episode_length(mdp, pi, T) == pytest.approx(2 * (1 - 0.5**T), abs=1e-15)
    # discounted: V = 0.5 (1 + 0.9 V)  =>  V = 0.5 / (1 - 0.45)
    assert float(policy_evaluation(mdp, pi)[0]) == pytest.approx(0.5 / 0.55, abs=1e-15)
    assert float(mdp.goal[1]) and not bool(mdp.goal[0])


def test_state_distributions_are_distributions(lake, expert_table):
    d = state_distributions(lake, expert_table, 30)
    assert d.shape == (31, 16)
    assert torch.allclose(d.sum(1), torch.ones(31, dtype=torch.float64), atol=1e-12)
    assert torch.equal(d[0], lake.initial)
    # success grows with the horizon and tends to the absorption probability
    s = [success_probability(lake, expert_table, T) for T in (10, 100, 1000, 5000)]
    assert s == sorted(s) and s[-1] == pytest.approx(32 / 41, abs=1e-9)


def test_stochastic_policy_rows_are_averaged(lake, expert_table):
    uniform = torch.full((16, 4), 0.25, dtype=torch.float64)
    mixed = 0.5 * uniform + 0.5 * torch.nn.functional.one_hot(expert_table, 4).double()
    a = success_probability(lake, uniform, 100)
    b = success_probability(lake, expert_table, 100)
    m = success_probability(lake, mixed, 100)
    assert a < m < b


def test_total_variation_and_occupancy(lake, expert_table):
    p = torch.tensor([0.5, 0.5, 0.0])
    q = torch.tensor([0.0, 0.5, 0.5])
    assert float(total_variation(p, q)) == 0.5
    assert float(total_variation(p, p)) == 0.0
    occ = occupancy(lake, expert_table, 20)
    d = state_distributions(lake, expert_table, 20)
    assert torch.allclose(occ, d[1:].mean(0)) and float(occ.sum()) == pytest.approx(1.0)
    occ0 = occupancy(lake, expert_table, 20, include_initial=True)
    assert torch.allclose(occ0, d[:-1].mean(0))


def test_reachable_states(lake, expert_table):
    any_policy = reachable_states(lake)
    frozen = any_policy & ~lake.terminal
    assert int(frozen.sum()) == 11  # the lake's 11 frozen cells, start included
    under_expert = reachable_states(lake, expert_table)
    assert (under_expert <= any_policy).all()
    # a policy that always goes LEFT from the start can never reach the goal's column
    left = torch.zeros(16, dtype=torch.long)
    assert not bool(reachable_states(lake, left)[15])


def test_cliffwalking_shortest_path_is_exact():
    mdp = TabularMDP.from_gym("CliffWalking-v1", 0.99)
    pi = greedy(mdp.backup(value_iteration(mdp, 500)[-1]))
    # 13 moves of -1 along the cliff edge; the goal is the only terminal state
    assert expected_return(mdp, pi, 100) == pytest.approx(-13.0, abs=1e-12)
    assert success_probability(mdp, pi, 13) == 1.0 and success_probability(mdp, pi, 12) == 0.0
    assert int(mdp.terminal.sum()) == 1 and bool(mdp.goal[47])


def test_other_toy_text_envs_build_valid_models():
    for env_id, kwargs in [
        ("FrozenLake-v1", {"map_name": "8x8"}),
        ("FrozenLake-v1", {"desc": ["SFH", "FFF", "HFG"], "is_slippery": False}),
        ("Taxi-v4", {}),
    ]:
        mdp = TabularMDP.from_gym(env_id, 0.9, make_kwargs=kwargs)
        assert torch.allclose(
            mdp.P.sum(-1), torch.ones(mdp.num_states, mdp.num_actions, dtype=torch.float64)
        )
        t = torch.nonzero(mdp.terminal).view(-1)
        assert t.numel() > 0
        assert (mdp.P[t, :, t] == 1.0).all() and (mdp.r[t] == 0).all()
    deterministic = TabularMDP.from_gym(
        "FrozenLake-v1", 1.0, make_kwargs={"desc": ["SFH", "FFF", "HFG"], "is_slippery": False}
    )
    # DOWN, RIGHT, DOWN, RIGHT reaches G in 4 steps with certainty: 1 0 2 1 2 ...
    pi = torch.tensor([1, 1, 0, 2, 1, 1, 0, 2, 0])
    assert success_probability(deterministic, pi, 4) == 1.0
    assert success_probability(deterministic, pi, 3) == 0.0


def test_greedy_expert_matches_the_numpy_reference_on_random_maps():
    """Mathematical ties break as in the textbook's numpy ``r + gamma * P @ V`` on every map."""
    import gymnasium as gym
    from gymnasium.envs.toy_text.frozen_lake import generate_random_map

    for size, seed in [(4, 1), (4, 5), (4, 17), (5, 2), (6, 10), (8, 1), (8, 2), (8, 27)]:
        env = gym.make(
            "FrozenLake-v1", desc=generate_random_map(size=size, seed=seed), is_slippery=True
        )
        S = env.observation_space.n
        P, r = np.zeros((S, 4, S)), np.zeros((S, 4))
        for s, actions in env.unwrapped.P.items():
            for a, outcomes in actions.items():
                for p, s_next, reward, _ in outcomes:
                    P[s, a, s_next] += p
                    r[s, a] += p * reward
        V = np.zeros(S)
        for _ in range(1000):
            V = (r + 0.95 * P @ V).max(axis=1)
        reference = (r + 0.95 * P @ V).argmax(axis=1)
        mdp = TabularMDP.from_gym(env, 0.95)
        ours = greedy(mdp.backup(value_iteration(mdp, 1000)[-1]))
        assert ours.tolist() == reference.tolist(), (size, seed)


def test_goal_is_the_best_terminal_entry_even_when_all_are_negative():
    # state 0 -> terminal 1 (reward -1) or terminal 2 (reward -5), half and half
    P = np.zeros((3, 1, 3))
    P[0, 0, 1:] = 0.5
    P[1, 0, 1] = P[2, 0, 2] = 1.0
    R = np.zeros((3, 1, 3))
    R[0, 0, 1], R[0, 0, 2] = -1.0, -5.0
    mdp = TabularMDP.from_arrays(P, R, 0.9, terminal=[False, True, True])
    assert mdp.goal.tolist() == [False, True, False]
    assert success_probability(mdp, torch.zeros(3, dtype=torch.long), 1) == 0.5
