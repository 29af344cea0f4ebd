"""The optimal expert of a toy-text env, by value iteration on the env's own model.

``value_iteration_expert("FrozenLake-v1")``. gymnasium's toy-text envs (FrozenLake, CliffWalking, Taxi) publish their dynamics as
``env.unwrapped.P``; :meth:`~imitrl.tabular.TabularMDP.from_gym` reads it, value
iteration solves it, and the expert acts greedily on the result (ties to the lowest
action). It is the expert of the FrozenLake study (:mod:`imitrl.experiments.frozenlake`),
with the study's discount and sweeps (declared once, in
:mod:`imitrl.configs.value_iteration`), and it answers for any state:
a queryable expert for DAgger.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

from imitrl.configs.value_iteration import VALUE_ITERATION_GAMMA, VALUE_ITERATION_SWEEPS
from imitrl.policies.experts import Expert
from imitrl.tabular.dp import greedy, value_iteration
from imitrl.tabular.mdp import TabularMDP

__all__ = ["value_iteration_expert"]


def value_iteration_expert(
    env: str | gym.Env,
    env_kwargs: Mapping[str, Any] | None = None,
    *,
    gamma: float = VALUE_ITERATION_GAMMA,
    sweeps: int = VALUE_ITERATION_SWEEPS,
) -> Expert:
    """The greedy policy of the optimal values of ``env``'s own model, as an
    :class:`~imitrl.policies.Expert` reading integer states and writing
    ``expert_action``.

    Args:
        env: a gymnasium id (``"FrozenLake-v1"``) or a toy-text env instance.
        env_kwargs: ``gym.make`` keyword arguments (``{"map_name": "8x8"}``,
            ``{"is_slippery": False}``, ``{"desc": [...]}``), as the env was made with.
        gamma: the discount of the values the expert is greedy on.
        sweeps: value-iteration sweeps.

    Raises:
        ValueError: an env without a tabular model (``unwrapped.P``), a malformed one,
            or ``gamma`` outside ``(0, 1]``.
    """
    mdp = TabularMDP.from_gym(env, gamma, make_kwargs=env_kwargs)
    return Expert.from_table(greedy(mdp.backup(value_iteration(mdp, sweeps)[-1])))
