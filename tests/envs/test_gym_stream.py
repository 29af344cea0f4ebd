"""The bulk stream player equals a step-by-step gymnasium loop, episode for episode."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from imitrl.envs.gym_stream import GymnasiumStream, play_episodes
from imitrl.tabular import TabularMDP, greedy, value_iteration


def _gym_episodes(env, table, n):
    rows, visited = [], []
    for _ in range(n):
        s, done, ret, length = env.reset()[0], False, 0.0, 0
        while not done:
            visited.append(s)
            s, r, term, trunc, _ = env.step(int(table[s]))
            done, ret, length = term or trunc, ret + r, length + 1
        rows.append((ret, length, trunc))
    return rows, visited


@pytest.fixture(params=["scalar", "batched"])
def path(request, monkeypatch):
    """Run each test through both implementations of play_episodes."""
    from imitrl.envs import gym_stream

    monkeypatch.setattr(gym_stream, "_SCALAR_LIMIT", 10**12 if request.param == "scalar" else 0)
    return request.param


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("FrozenLake-v1", {}),
        ("FrozenLake-v1", {"map_name": "8x8"}),
        ("FrozenLake-v1", {"desc": ["SFFF", "FHFH", "FFFF", "HFFG"], "success_rate": 0.6}),
        ("CliffWalking-v1", {"max_episode_steps": 80}),
    ],
)
def test_stream_equals_gymnasium_loop(env_id, kwargs, path):
    genv = gym.make(env_id, **kwargs)
    mdp = TabularMDP.from_gym(genv, 0.95)
    expert = greedy(mdp.backup(value_iteration(mdp, 500)[-1]))
    rng = np.random.default_rng(5)
    policies = [expert, torch.as_tensor(rng.integers(0, mdp.num_actions, mdp.num_states))]
    for seed, table in zip((3, 9), policies):
        genv.reset(seed=seed)
        stream = GymnasiumStream(seed)
        # two consecutive blocks share one stream, as the section's experiments do
        for n in (40, 25, 130):
            ref, visited = _gym_episodes(genv, table.tolist(), n)
            got = play_episodes(mdp, table, stream, n, record=True)
            assert got.returns.tolist() == [float(r) for r, _, _ in ref]
            assert got.lengths.tolist() == [length for _, length, _ in ref]
            assert got.truncated.tolist() == [t for _, _, t in ref]
            assert got.observations.tolist() == visited
            assert torch.equal(got.actions, table[got.observations])


def test_success_flag_marks_goal_entries(lake, expert_table, path):
    eps = play_episodes(lake, expert_table, GymnasiumStream(1), 300)
    assert torch.equal(eps.success, eps.returns > 0)
    assert not (eps.success & eps.truncated).any()


def test_stream_position_advances_by_resets_plus_steps(lake, expert_table, path):
    stream = GymnasiumStream(0)
    assert stream.position == 1  # the seeded reset consumed one uniform
    eps = play_episodes(lake, expert_table, stream, 10)
    assert stream.position == 1 + 10 + int(eps.lengths.sum())


def test_stochastic_policy_rejected(lake):
    with pytest.raises(ValueError, match="deterministic policy"):
        play_episodes(lake, torch.full((16, 4), 0.25), GymnasiumStream(0), 3)


def test_needs_a_time_limit():
    mdp = TabularMDP.from_gym("CliffWalking-v1", 0.9)
    with pytest.raises(ValueError, match="no time limit"):
        play_episodes(mdp, torch.zeros(48, dtype=torch.long), GymnasiumStream(0), 1)
