"""Exact tabular toolkit: MDPs as dense float64 tensors and pure functions over them.

Modules import one way, lower to higher: ``validation`` and ``bellman`` (numpy/torch
only) -> ``gym_model`` -> ``mdp`` -> ``policy`` -> ``dp`` and ``finite_horizon``;
``sampling`` reads ``mdp`` only; ``maxent_irl`` reads ``mdp`` and ``finite_horizon``;
``airl`` (imported as a module: ``imitrl.tabular.airl``) reads ``mdp`` and ``sampling``.
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
from imitrl.tabular.maxent_irl import (
    Demonstrations,
    IRLResult,
    SoftPolicy,
    dual_objective,
    feature_expectations,
    likelihood_gradient,
    linear_reward,
    log_likelihood,
    maxent_irl,
    next_state_features,
    occupancy_measure,
    soft_value_iteration,
    state_action_features,
    state_features,
    time_indexed_state_distributions,
)
from imitrl.tabular.mdp import Outcomes, TabularMDP
from imitrl.tabular.policy import kernel_under, policy_probs, reward_under
from imitrl.tabular.sampling import OutcomeSampler

__all__ = [
    "Demonstrations",
    "IRLResult",
    "OutcomeSampler",
    "Outcomes",
    "SoftPolicy",
    "TabularMDP",
    "backup",
    "dual_objective",
    "expected_episode_length",
    "expected_return",
    "feature_expectations",
    "greedy",
    "kernel_under",
    "likelihood_gradient",
    "linear_reward",
    "log_likelihood",
    "maxent_irl",
    "next_state_features",
    "occupancy",
    "occupancy_measure",
    "policy_evaluation",
    "policy_probs",
    "reachable_states",
    "reward_under",
    "soft_value_iteration",
    "state_action_features",
    "state_distributions",
    "state_features",
    "success_probability",
    "time_indexed_state_distributions",
    "total_variation",
    "value_iteration",
]
