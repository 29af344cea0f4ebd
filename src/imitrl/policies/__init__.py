"""Policies as TensorDict modules: experts, the ActorCritic container, the DAgger mixture."""

from imitrl.policies.actor_critic import HEADS, ActorCritic
from imitrl.policies.distributions import GreedyCategorical
from imitrl.policies.experts import Expert, TableLookup, as_actor
from imitrl.policies.mixture import BetaMixer, behaviour_policy

__all__ = [
    "HEADS",
    "ActorCritic",
    "BetaMixer",
    "Expert",
    "GreedyCategorical",
    "TableLookup",
    "as_actor",
    "behaviour_policy",
]
