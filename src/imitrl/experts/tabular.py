"""The optimal expert of a toy-text env, by value iteration on the env's own model.

``value_iteration_expert("FrozenLake-v1")``. gymnasium's toy-text envs (FrozenLake,
CliffWalking, Taxi) publish their dynamics as ``env.unwrapped.P``;
:meth:`~imitrl.tabular.TabularMDP.from_gym` reads it, value iteration solves it, and the
expert acts greedily on the result (ties to the lowest action). It is the expert of the
FrozenLake study (:mod:`imitrl.experiments.frozenlake`), at the study's discount
(declared once, in :mod:`imitrl.configs.value_iteration`), swept until its values
converge, and it answers for any state: a queryable expert for DAgger. It is optimal for
the discounted return; on a lake with a time limit, a policy maximising the chance of
reaching the goal within it may do better (on the 8x8 map within 200 steps, 0.886
exactly against this expert's 0.739).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

from imitrl.configs.value_iteration import VALUE_ITERATION_GAMMA, VALUE_ITERATION_SWEEPS
from imitrl.policies.experts import Expert
from imitrl.tabular.dp import converged_values, greedy, value_iteration
from imitrl.tabular.mdp import TabularMDP

__all__ = ["value_iteration_expert"]


def value_iteration_expert(
    env: str | gym.Env,
    env_kwargs: Mapping[str, Any] | None = None,
    *,
    gamma: float = VALUE_ITERATION_GAMMA,
    sweeps: int | None = None,
) -> Expert:
    """The greedy policy of the optimal values of ``env``'s own model, as an
    :class:`~imitrl.policies.Expert` reading integer states and writing
    ``expert_action``.

    Args:
        env: a gymnasium id (``"FrozenLake-v1"``) or a toy-text env instance.
        env_kwargs: ``gym.make`` keyword arguments (``{"map_name": "8x8"}``,
            ``{"is_slippery": False}``, ``{"desc": [...]}``), as the env was made with.
        gamma: the discount of the values the expert is greedy on.
        sweeps: value-iteration sweeps; None (the default): until the values converge
            (:func:`~imitrl.tabular.dp.converged_values`, at most the states plus
            ``10 x`` :data:`~imitrl.configs.value_iteration.VALUE_ITERATION_SWEEPS`), so a
            state farther from the goal than any fixed number of sweeps is not left with
            its actions tied; the study's ``--vi-iters`` gives a fixed number.

    Raises:
        ValueError: an env without a tabular model (``unwrapped.P``), a malformed one,
            ``gamma`` outside ``(0, 1]``, or values that do not converge.
    """
    mdp = TabularMDP.from_gym(env, gamma, make_kwargs=env_kwargs)
    if sweeps is None:
        V, _ = converged_values(mdp, mdp.num_states + 10 * VALUE_ITERATION_SWEEPS)
    else:
        V = value_iteration(mdp, sweeps)[-1]
    return Expert.from_table(greedy(mdp.backup(V)))
