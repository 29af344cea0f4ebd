"""Exact tabular toolkit: MDPs as dense float64 tensors and pure functions over them.

Modules import one way, lower to higher: ``validation`` and ``bellman`` (numpy/torch
only) -> ``gym_model`` -> ``mdp`` -> ``policy`` -> ``dp`` and ``finite_horizon``;
``sampling`` reads ``mdp`` only.
"""

from imitrl.tabular.dp import backup, greedy, policy_evaluation, value_iteration
from imitrl.tabular.finite_horizon import (
    expected_episode_length,
    expected_return,
    occupancy,
    reachable_states,
    state_distributions,
    success_probability,
    total_variation,
)
from imitrl.tabular.mdp import Outcomes, TabularMDP
from imitrl.tabular.policy import kernel_under, policy_probs, reward_under
from imitrl.tabular.sampling import OutcomeSampler

__all__ = [
    "OutcomeSampler",
    "Outcomes",
    "TabularMDP",
    "backup",
    "expected_episode_length",
    "expected_return",
    "greedy",
    "kernel_under",
    "occupancy",
    "policy_evaluation",
    "policy_probs",
    "reachable_states",
    "reward_under",
    "state_distributions",
    "success_probability",
    "total_variation",
    "value_iteration",
]
