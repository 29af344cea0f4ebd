"""Built-in queryable experts (TensorDict modules writing ``expert_action``)."""

from imitrl.experts.classic_control import CARTPOLE_GAINS, cartpole_expert

__all__ = ["CARTPOLE_GAINS", "cartpole_expert"]
