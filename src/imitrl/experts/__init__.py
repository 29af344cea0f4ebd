"""Built-in queryable experts: every builder returns an :class:`imitrl.policies.Expert`.

Classic control and the toy-text envs (:func:`value_iteration_expert`: the optimal
policy of the env's own model) need only gymnasium; building a MuJoCo expert
(``imitrl.experts.mujoco``) needs the ``mujoco`` extra, a Meta-World one
(:func:`metaworld_expert`) the ``metaworld`` extra.
"""

from imitrl.experts.classic_control import (
    CARTPOLE_GAINS,
    PENDULUM,
    PendulumSwingUp,
    acrobot_expert,
    cartpole_expert,
    mountaincar_expert,
    pendulum_expert,
    pendulum_linearization,
)
from imitrl.experts.lqr import LinearFeedback, dlqr
from imitrl.experts.metaworld import metaworld_expert
from imitrl.experts.mujoco import (
    Linearization,
    inverted_double_pendulum_expert,
    inverted_pendulum_expert,
    linearize_mujoco,
)
from imitrl.experts.tabular import value_iteration_expert

__all__ = [
    "CARTPOLE_GAINS",
    "PENDULUM",
    "LinearFeedback",
    "Linearization",
    "PendulumSwingUp",
    "acrobot_expert",
    "cartpole_expert",
    "dlqr",
    "inverted_double_pendulum_expert",
    "inverted_pendulum_expert",
    "linearize_mujoco",
    "metaworld_expert",
    "mountaincar_expert",
    "pendulum_expert",
    "pendulum_linearization",
    "value_iteration_expert",
]
