"""The value-iteration expert of a toy-text env (``--expert value_iteration``, what
``--expert auto`` gives FrozenLake, CliffWalking and Taxi)."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.configs.value_iteration import VALUE_ITERATION_GAMMA, VALUE_ITERATION_SWEEPS
from imitrl.experiments.frozenlake.config import StudyConfig
from imitrl.experts import value_iteration_expert
from imitrl.tabular import TabularMDP, success_probability
from tests.tabular.test_tabular_exact import SEED_EXPERT


def _table(expert, states: int) -> list[int]:
    td = TensorDict({keys.OBSERVATION: torch.arange(states)}, batch_size=[states])
    return expert(td)[keys.EXPERT_ACTION].tolist()


def test_the_frozenlake_expert_is_the_studys_and_the_settings_are_declared_once():
    assert _table(value_iteration_expert("FrozenLake-v1"), 16) == SEED_EXPERT
    study = StudyConfig()
    assert (study.gamma, study.vi_iters) == (VALUE_ITERATION_GAMMA, VALUE_ITERATION_SWEEPS)


def test_a_map_of_env_kwargs_is_solved_as_made():
    """The deterministic 8x8 lake: the expert reaches the goal with probability 1 (exact,
    from the model), within the shortest path's 14 steps; a slippery expert does not."""
    kwargs = {"map_name": "8x8", "is_slippery": False}
    table = torch.tensor(_table(value_iteration_expert("FrozenLake-v1", kwargs), 64))
    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs=kwargs)
    assert success_probability(mdp, table, 14) == 1.0
    assert success_probability(mdp, table, 13) == 0.0
    slippery = torch.tensor(
        _table(value_iteration_expert("FrozenLake-v1", {"map_name": "8x8"}), 64)
    )
    assert success_probability(mdp, slippery, 14) < 1.0


def test_the_cliffwalking_expert_walks_the_shortest_path_beside_the_cliff():
    """The optimal return of CliffWalking is -13 (13 steps, none off the cliff)."""
    expert = value_iteration_expert("CliffWalking-v1")
    env = gym.make("CliffWalking-v1")
    obs, _ = env.reset(seed=0)
    total, done, steps = 0.0, False, 0
    while not done and steps < 100:
        action = _table(expert, 48)[obs]
        obs, reward, terminated, truncated, _ = env.step(action)
        total, done, steps = total + float(reward), terminated or truncated, steps + 1
    assert (total, steps) == (-13.0, 13)


def test_an_env_without_a_model_is_refused():
    with pytest.raises(ValueError, match="CartPole-v1"):
        value_iteration_expert("CartPole-v1")


def test_a_goal_farther_than_a_fixed_number_of_sweeps_is_still_found():
    """A hostile review: 1000 fixed sweeps left every state more than 1000 steps from the
    goal at value 0, its actions tied, and the expert walked left forever (return 0 on a
    snake-shaped 47x47 map). Here 40 sweeps on a 60-cell corridor show the same: fixed
    sweeps tie the far end; the expert sweeps until its values converge."""
    from imitrl.tabular import TabularMDP, greedy, value_iteration

    kwargs = {"desc": ["S" + "F" * 58 + "G"], "is_slippery": False}
    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs=kwargs)
    fixed = greedy(mdp.backup(value_iteration(mdp, 40)[-1]))
    assert fixed[0].item() == 0  # LEFT: the start's actions all tied at 0
    table = _table(value_iteration_expert("FrozenLake-v1", kwargs), 60)
    assert table[:59] == [2] * 59  # RIGHT, all the way
    assert success_probability(mdp, torch.tensor(table), 59) == 1.0
    with pytest.raises(ValueError, match="did not converge in 40 sweeps"):
        from imitrl.tabular.dp import converged_values

        converged_values(mdp, 40)
